"""The learned prior: held-out procedural patches, and scene reconstruction against TSDF fusion.

    python -m benchmarks.bench_prior [--quick] [--threads N] [--weights PATH] [--no-scenes]

Writes ``benchmarks/results/prior.md``.

1. Held-out patches (``mapping.training.train.heldout_batches``'s seeds, never trained on): SDF
   error near the surface and within the training clamp, sign accuracy and predicted sigma, for
   the shipped prior, the analytic tangent-plane prior and a random initialisation.
2. Patch meshing: each patch's field marched on the 0.25 vu lattice, exact SDF at the vertices.
3. Scenes (RGB-D, ground-truth poses): the generated room, Replica office0, 7-Scenes redkitchen;
   our map (V = 0.1 m) against OpenCV's HashTSDF at 2.5 and 10 cm, by accuracy, completion and
   completion ratio (< 5 cm) against the ground-truth mesh (7-Scenes: the 2.5 cm TSDF surface).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.harness.cli import bench_parser, command_line, start_logging
from benchmarks.harness.machine import section_header
from benchmarks.harness.paths import DATA, RESULTS_DIR
from benchmarks.harness.reference import tsdf
from benchmarks.harness.repeat import REPEATS, Timing, repeats_line
from benchmarks.harness.results import table
from common.atomic_io import write_text_atomic
from common.geometry import orthonormalize
from mapping.networks import DEFAULT_WEIGHTS, PriorModel
from mapping.training.scenes import PATCH_KINDS
from mapping.training.train import EVAL_SEED_BASE, encode_patches, evaluate, heldout_sets

log = logging.getLogger("benchmarks.bench_prior")

VOXEL_M = 0.1
THRESHOLD_M = 0.05


# ---------------------------------------------------------------------------- models
def load_models(weights: Path) -> list[tuple[str, PriorModel]]:
    from mapping.analytic_prior import planar_prior

    models = []
    cfg = None
    if weights.is_file():
        shipped = PriorModel.load(weights).eval()
        cfg = shipped.cfg
        models.append(("shipped prior", shipped))
    else:
        log.warning("%s not found: only baselines are measured", weights)
    models.append(("tangent-plane prior (analytic)", planar_prior().eval()))
    torch.manual_seed(0)
    models.append(("random init (seed 0)", PriorModel(cfg).eval()))
    return models


# ---------------------------------------------------------------------------- patches
def patch_section(models, sets, lines: list[str]) -> None:
    batches = [b for b, _ in sets]
    n = sum(b.points.shape[0] for b in batches)
    rows = []
    for name, model in models:
        m = evaluate(model, batches, 0.1, 0.5)
        rows.append(
            [
                name,
                *(f"{m[k]:.4f}" for k in ("mae_near_vu", "mae_clamp_vu")),
                *(f"{m[k]:.3f}" for k in ("sign_accuracy", "sigma_near_vu")),
            ]
        )
    kinds = []
    for k, kind in enumerate(PATCH_KINDS):
        row = [kind, sum(int((b.kind == k).sum()) for b in batches)]
        for _, model in models:
            err, num = 0.0, 0
            for b in batches:
                with torch.no_grad():
                    mean, _ = model.decoder(encode_patches(model, b), b.queries)
                sel = b.sdf_mask & (b.sdf.abs() < 0.1) & (b.kind == k)[:, None]
                err += (mean - b.sdf).abs()[sel].sum().item()
                num += int(sel.sum())
            row.append(f"{err / max(num, 1):.4f}")
        kinds.append(row)
    header = (
        "model | mean abs err, abs SDF < 0.1 vu | mean abs err, abs SDF < 0.5 vu | sign "
        "accuracy (abs SDF < 0.5 vu) | mean sigma, abs SDF < 0.1 vu"
    )
    lines += [
        "### Held-out procedural patches",
        "",
        f"{n} patches (seeds from {EVAL_SEED_BASE}, 4096 SDF samples each, generator defaults); "
        "errors in voxel units (vu; 1 vu = 10 cm at V = 0.1 m).",
        "",
        *table(header, rows),
        "",
        "Per kind (mean abs err for abs SDF < 0.1 vu):",
        "",
        *table("kind | patches | " + " | ".join(name for name, _ in models), kinds),
        "",
    ]


@torch.no_grad()
def lattice_mesh_errors(model: PriorModel, sets) -> tuple[float, float, float, int]:
    """Marching cubes on the 0.25 vu lattice of each patch, exact |SDF| at the vertices in the
    voxel: mean (vu), 90th percentile, fraction beyond 0.1 vu, and the number of vertices."""
    from skimage.measure import marching_cubes

    axis = torch.linspace(-1.0, 1.0, 9)
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    errors = []
    for batch, scenes in sets:
        F = encode_patches(model, batch)
        mean, _ = model.decoder(F, grid.expand(F.shape[0], -1, -1))
        for b in range(F.shape[0]):
            volume = mean[b].reshape(9, 9, 9).numpy()
            if volume.min() >= 0 or volume.max() <= 0:
                continue
            verts, _, _, _ = marching_cubes(volume, 0.0, spacing=(0.25, 0.25, 0.25))
            verts = verts - 1.0
            inside = np.abs(verts).max(1) <= 0.5
            if not inside.any():
                continue
            v = torch.as_tensor(verts[inside], dtype=torch.float32)
            patch_scene = _one_scene(scenes, b)
            errors.append(patch_scene.sdf(v[None])[0].abs().numpy())
    e = np.concatenate(errors) if errors else np.zeros(0)
    if len(e) == 0:
        return float("nan"), float("nan"), float("nan"), 0
    return float(e.mean()), float(np.percentile(e, 90)), float((e > 0.1).mean()), len(e)


def _one_scene(scenes, b: int):
    from mapping.training.scenes import Scenes

    fields = ("kind", "params", "sign", "active", "R", "t")
    return Scenes(**{name: getattr(scenes, name)[b : b + 1] for name in fields})


def lattice_section(models, sets, lines: list[str]) -> None:
    rows = []
    for name, model in models:
        mean, p90, frac, count = lattice_mesh_errors(model, sets)
        rows.append([name, count, f"{mean:.4f}", f"{p90:.4f}", f"{100 * frac:.1f} %"])
    header = (
        "model | vertices | mean abs SDF at vertices (vu) | 90th percentile (vu) | "
        "vertices > 0.1 vu off"
    )
    lines += [
        "### Patch meshing on the 0.25 vu lattice",
        "",
        "Each held-out patch's field decoded on the 9^3 lattice over the 2V cube (spacing 0.25 vu, "
        "as `mesh_subdivisions = 4`), marching cubes at 0, and the exact |SDF| of the scene at the "
        "vertices inside the central voxel (no sigma filtering; far sides of one-sided "
        "observations count as errors).",
        "",
        *table(header, rows),
        "",
    ]


# ---------------------------------------------------------------------------- scenes
def _frames_of(source, every: int, limit: int) -> list:
    frames = []
    for i in range(0, len(source), every):
        frames.append(source[i])
        frames[-1].T_W_S_gt = orthonormalize(frames[-1].T_W_S_gt)
        if len(frames) >= limit:
            break
    return frames


def run_ours(model: PriorModel, frames: list):
    from mapping.config import MapConfig
    from mapping.neural_map import NeuralMap

    nm = NeuralMap(MapConfig(voxel_size_m=VOXEL_M, device="cpu"), model)
    t0 = time.perf_counter()
    for i, frame in enumerate(frames):
        nm.fuse(nm.encode(i, frame.points, frame.normals, frame.T_W_S_gt))
    build = time.perf_counter() - t0
    t0 = time.perf_counter()
    mesh = nm.extract_mesh()
    return mesh, nm.memory_bytes(), build, time.perf_counter() - t0


def points_metrics(points: np.ndarray, gt, gt_samples: np.ndarray) -> tuple[float, float, float]:
    """Accuracy of ``points`` against the ``gt`` mesh (or, where it is None, the reference points
    ``gt_samples``), completion of ``gt_samples`` to the nearest point, and the ratio < 5 cm."""
    from scipy.spatial import cKDTree

    from slam.evaluation.metrics.mesh import surface_distances

    sub = points[np.random.default_rng(1).choice(len(points), min(len(points), 100_000))]
    if gt is None:
        acc = cKDTree(gt_samples).query(sub, workers=-1)[0]
    else:
        acc = surface_distances(sub, gt)
    comp, _ = cKDTree(points).query(gt_samples, workers=-1)
    return float(acc.mean()), float(comp.mean()), float((comp < THRESHOLD_M).mean())


def mesh_scores(mesh, gt, gt_samples: np.ndarray) -> tuple[float, float, float]:
    """:func:`points_metrics` of a mesh: against the ``gt`` mesh surface both ways, or (``gt``
    None) 200k samples of it against the reference points."""
    import trimesh

    from slam.evaluation.metrics.mesh import surface_distances

    if len(mesh.faces) == 0:
        return float("inf"), float("inf"), 0.0
    if gt is None:
        return points_metrics(
            trimesh.sample.sample_surface(mesh, 200_000, seed=0)[0], None, gt_samples
        )
    acc = surface_distances(trimesh.sample.sample_surface(mesh, 100_000, seed=0)[0], gt)
    comp = surface_distances(gt_samples, mesh)
    return float(acc.mean()), float(comp.mean()), float((comp < THRESHOLD_M).mean())


def _repeated(build_and_extract) -> tuple:
    """``build_and_extract()`` (a map, its memory, build and extraction seconds) ``REPEATS``
    times: the first map and memory, the seconds as :class:`Timing` values."""
    runs = [build_and_extract() for _ in range(REPEATS)]
    return (*runs[0][:2], *(Timing(run[k] for run in runs) for k in (2, 3)))


def evaluate_scene(name: str, frames: list, gt, models, lines: list[str], note: str) -> None:
    """One table of the TSDFs and our maps of ``frames``; without a ``gt`` mesh the 2.5 cm TSDF
    surface is the reference."""
    import trimesh

    from slam.evaluation.metrics.mesh import visible_face_mask

    def cells(method, scores, mem, build, extract):
        acc, comp, ratio = scores or ("(reference)",) * 3
        if scores is not None:
            acc, comp, ratio = f"{100 * acc:.2f}", f"{100 * comp:.2f}", f"{100 * ratio:.1f} %"
        return [method, acc, comp, ratio, f"{mem / 1e6:.2f}", f"{build:.1f}", f"{extract:.1f}"]

    tsdfs = {v: _repeated(lambda v=v: tsdf(frames, v, 1_000_000)) for v in (0.025, 0.1)}
    if gt is None:
        ref_pts = tsdfs[0.025][0]
        rng = np.random.default_rng(2)
        gt_samples = ref_pts[rng.choice(len(ref_pts), min(len(ref_pts), 100_000), replace=False)]
    else:
        intr = frames[0].intrinsics
        poses = np.stack([f.T_W_S_gt for f in frames])
        mask = visible_face_mask(gt, poses, intr.K, intr.width, intr.height)
        gt_samples, _ = trimesh.sample.sample_surface(
            gt, 100_000, face_weight=gt.area_faces * mask, seed=3
        )
    rows = []
    for voxel, (pts, *cost) in tsdfs.items():
        scores = None if gt is None and voxel == 0.025 else points_metrics(pts, gt, gt_samples)
        rows.append(cells(f"TSDF {voxel * 100:g} cm", scores, *cost))
    for label, model in models:
        log.info("%s: neural map with %s", name, label)
        mesh, *cost = _repeated(lambda model=model: run_ours(model, frames))
        scores = mesh_scores(mesh, gt, gt_samples)
        rows.append(cells(f"ours, {label}, V = {VOXEL_M * 100:g} cm", scores, *cost))
    header = (
        "method | accuracy (cm) | completion (cm) | completion ratio < 5 cm | map memory "
        "(MB) | integrate (s) | surface extraction (s)"
    )
    lines += [f"#### {name}", "", note, "", *table(header, rows), ""]


def scenes_section(models, quick: bool, lines: list[str]) -> None:
    import trimesh

    from frontends.sources import make_source

    # depth pixels kept for our map on the large real images (TSDF integrates full images); the
    # 320x240 generated room always uses every 2nd pixel, as configs/demo.yaml
    stride = 4 if quick else 2
    lines += [
        "### Scenes: neural map vs TSDF fusion (ground-truth poses)",
        "",
        "Ours: every frame is a submap (its depth points with normals from `frontends.depth`, "
        f"pixel stride {stride} on the real images, 2 on the generated ones), "
        f"encoded and fused at V = {VOXEL_M * 100:g} cm, meshed with the default `MapConfig` "
        "(4 lattice cells per voxel, sigma cut 0.15 vu, min weight 8). TSDF: OpenCV 5 "
        "`cv2.Volume(VolumeType_HashTSDF)`, truncation 4 voxels, surface by ray-casting from "
        "each input pose. Map memory: ours `NeuralMap.memory_bytes()`; TSDF estimated as "
        "allocated 16^3-voxel units x 2 bytes per voxel. Distances from 100k samples; "
        "TSDF completion to the nearest ray-cast point.",
        "",
        repeats_line(
            "Each map is built and extracted that often; the accuracy is the first's "
            "(the same in every run)."
        ),
        "",
    ]
    scenes = []
    try:
        # the demo's sequence (configs/demo.yaml), so the cached copy is reused
        room_depth = {"stride": 2, "max_depth_m": 6.0}
        src = make_source(
            "generated",
            kind="rgbd",
            num_frames=240,
            width=320,
            height=240,
            loader_options={"depth_options": room_depth},
        )
        note = (
            "generated room; completion is over every ground-truth face inside some camera "
            "frustum, occluded ones included, so it is high for every method"
        )
        frames = _frames_of(src, 24 if quick else 8, 30)
        scenes.append(("Generated RGB-D room", frames, trimesh.load(src.gt_mesh_path), note))
    except Exception as exc:  # report, do not stop the other scenes
        lines += [f"Generated room skipped: {exc.__class__.__name__}: {exc}", ""]
    replica, kitchen = DATA / "replica", DATA / "7scenes_redkitchen"
    depth = {"depth_options": {"stride": stride}}
    if quick:
        lines += ["Quick mode: the generated room only (no Replica, no 7-Scenes).", ""]
    for folder, name in () if quick else ((replica, "Replica"), (kitchen, "7-Scenes")):
        if not folder.is_dir():
            lines += [f"{name} skipped: {folder} not found.", ""]
    if not quick and replica.is_dir():
        src = make_source("replica", root=replica, sequence="office0", **depth)
        gt = trimesh.load(replica / "office0_mesh.ply")
        scenes.append(("Replica office0 (4 frames)", _frames_of(src, 1, 4), gt, "real data"))
    if not quick and kitchen.is_dir():
        src = make_source("7scenes", root=kitchen, sequence="seq-01", **depth)
        frames = _frames_of(src, 8, 50)
        scenes.append(("7-Scenes redkitchen", frames, None, "real data, no GT mesh"))
    for name, frames, gt, kind in scenes:
        note = f"{len(frames)} frames ({kind})."
        if gt is None:
            note += " No ground-truth mesh: the TSDF 2.5 cm surface is the reference."
        log.info("scene %s", name)
        try:
            evaluate_scene(name, frames, gt, models, lines, note)
        except Exception as exc:  # one failing scene must not lose the others
            log.exception("scene %s failed", name)
            lines += [f"#### {name}", "", f"Failed: {exc.__class__.__name__}: {exc}", ""]


def build_parser():
    parser = bench_parser(__doc__, "fewer patches and frames", out=RESULTS_DIR / "prior.md")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    parser.add_argument("--weights", type=Path, default=DEFAULT_WEIGHTS, help="prior weights")
    parser.add_argument("--no-scenes", action="store_true", help="only the patch sections")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    start_logging()
    torch.set_num_threads(args.threads)
    models = load_models(args.weights)
    shipped = models[0][1] if args.weights.is_file() else None
    weights = " (not found)"
    if shipped is not None:
        meta = getattr(shipped, "metadata", {})
        weights = (
            f" (identity {shipped.identity()}, {meta.get('steps')} steps, "
            f"{meta.get('train_wall_s')} s of training)"
        )
    title = "Learned prior (mapping/training/patches.py, mapping/training/train.py)"
    lines = [
        *section_header(title, command_line("bench_prior", argv)),
        f"- torch threads: {torch.get_num_threads()}, CPU only",
        f"- Weights: `{args.weights}`{weights}",
        "",
    ]
    sets = heldout_sets(32 if args.quick else 256)
    patch_section(models, sets, lines)
    lattice_section(models, sets, lines)
    if not args.no_scenes:
        scene_models = [m for m in models if not m[0].startswith("random")]
        scenes_section(scene_models[:1] if args.quick else scene_models, args.quick, lines)
    write_text_atomic(args.out, "\n".join(lines) + "\n")
    log.info("wrote %s", args.out)


if __name__ == "__main__":
    main()
