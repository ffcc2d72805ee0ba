"""The learned prior: held-out procedural patches, and scene reconstruction against TSDF fusion.

    python -m benchmarks.bench_prior [--quick] [--threads N] [--weights PATH] [--no-scenes]

Writes ``benchmarks/results/prior.md``.

1. Held-out patches (the fixed-seed set of ``mapping.training.train.heldout_batches``, never
trained on):
   mean |SDF error| near the surface (|SDF| < 0.1 vu) and within the training clamp, sign accuracy
   and mean predicted sigma, for the shipped prior, the analytic tangent-plane prior and a random
   initialisation; per patch kind for the shipped prior.
2. Patch meshing: each patch's field decoded on the 0.25 vu meshing lattice over the 2V cube,
   marching cubes, and the exact SDF at the vertices inside the central voxel.
3. Scenes (RGB-D with ground-truth poses, mapping only): the generated room, Replica office0 and
   7-Scenes redkitchen. Ours: one submap per frame, encoded and fused at V = 0.1 m, meshed by
   ``NeuralMap.extract_mesh``. Baselines: OpenCV 5 ``cv2.Volume`` HashTSDF at 2.5 cm and 10 cm
   voxels integrating the same depth images; its surface is read by ray-casting the volume from
   every input pose (``fetchPointsNormals`` of this build returns voxel positions, not surface
   points). Accuracy / completion / completion ratio (< 5 cm) against the ground-truth mesh
   (completion over the faces inside some camera frustum); 7-Scenes has no ground-truth mesh, so
   there the 2.5 cm TSDF surface is the reference.
"""

from __future__ import annotations

import argparse
import logging
import shlex
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from benchmarks.harness.machine import section_header
from benchmarks.harness.paths import DATA, RESULTS_DIR
from benchmarks.harness.reference import tsdf
from benchmarks.harness.repeat import REPEATS, Timing, repeats_line
from common.atomic_io import write_text_atomic
from common.geometry import orthonormalize
from mapping.networks import DEFAULT_WEIGHTS, PriorModel
from mapping.training.patches import PatchConfig, generate_patches_with_scenes
from mapping.training.scenes import PATCH_KINDS
from mapping.training.train import EVAL_SEED_BASE, encode_patches, evaluate

log = logging.getLogger("benchmarks.bench_prior")

RESULTS = RESULTS_DIR / "prior.md"
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
def heldout(n_patches: int) -> list:
    """The held-out set of mapping.training.train (same seeds), with the scenes kept for exact
    SDF."""
    cfg = PatchConfig()
    out, chunk = [], 64
    for i, start in enumerate(range(0, n_patches, chunk)):
        size = min(chunk, n_patches - start)
        out.append(generate_patches_with_scenes(size, EVAL_SEED_BASE + i, cfg))
    return out


def patch_section(models, sets, lines: list[str]) -> None:
    batches = [b for b, _ in sets]
    n = sum(b.points.shape[0] for b in batches)
    lines += [
        "### Held-out procedural patches",
        "",
        f"{n} patches (seeds from {EVAL_SEED_BASE}, 4096 SDF samples each, generator defaults); "
        "errors in voxel units (vu; 1 vu = 10 cm at V = 0.1 m).",
        "",
        "| model | mean abs err, abs SDF < 0.1 vu | mean abs err, abs SDF < 0.5 vu | sign accuracy "
        "(abs SDF < 0.5 vu) | mean sigma, abs SDF < 0.1 vu |",
        "|---|---|---|---|---|",
    ]
    for name, model in models:
        m = evaluate(model, batches, 0.1, 0.5)
        lines.append(
            f"| {name} | {m['mae_near_vu']:.4f} | {m['mae_clamp_vu']:.4f} | "
            f"{m['sign_accuracy']:.3f} | {m['sigma_near_vu']:.3f} |"
        )
    lines += ["", "Per kind (mean abs err for abs SDF < 0.1 vu):", ""]
    header = "| kind | patches | " + " | ".join(name for name, _ in models) + " |"
    lines += [header, "|---|---|" + "---|" * len(models)]
    for k, kind in enumerate(PATCH_KINDS):
        row = [kind]
        count = sum(int((b.kind == k).sum()) for b in batches)
        row.append(str(count))
        for _, model in models:
            err, num = 0.0, 0
            for b in batches:
                with torch.no_grad():
                    mean, _ = model.decoder(encode_patches(model, b), b.queries)
                sel = b.sdf_mask & (b.sdf.abs() < 0.1) & (b.kind == k)[:, None]
                err += (mean - b.sdf).abs()[sel].sum().item()
                num += int(sel.sum())
            row.append(f"{err / max(num, 1):.4f}")
        lines.append("| " + " | ".join(row) + " |")
    lines.append("")


@torch.no_grad()
def lattice_mesh_errors(model: PriorModel, sets) -> tuple[float, float, float, int]:
    """Marching cubes on the 0.25 vu lattice of each patch; exact |SDF| at vertices in the voxel.

    Returns mean |SDF| (vu), 90th percentile, fraction of vertices farther than 0.1 vu from the
    surface, and the number of vertices.
    """
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

    return Scenes(
        **{
            name: getattr(scenes, name)[b : b + 1]
            for name in ("kind", "params", "sign", "active", "R", "t")
        }
    )


def lattice_section(models, sets, lines: list[str]) -> None:
    lines += [
        "### Patch meshing on the 0.25 vu lattice",
        "",
        "Each held-out patch's field decoded on the 9^3 lattice over the 2V cube (spacing 0.25 vu, "
        "as `mesh_subdivisions = 4`), marching cubes at 0, and the exact |SDF| of the scene at the "
        "vertices inside the central voxel (no sigma filtering; far sides of one-sided "
        "observations count as errors).",
        "",
        "| model | vertices | mean abs SDF at vertices (vu) | 90th percentile (vu) | "
        "vertices > 0.1 vu off |",
        "|---|---|---|---|---|",
    ]
    for name, model in models:
        mean, p90, frac, count = lattice_mesh_errors(model, sets)
        lines.append(f"| {name} | {count} | {mean:.4f} | {p90:.4f} | {100 * frac:.1f} % |")
    lines.append("")


# ---------------------------------------------------------------------------- scenes
@dataclass
class SceneResult:
    method: str
    accuracy_m: float
    completion_m: float
    ratio: float
    memory_bytes: int
    build_s: float
    extract_s: float


def _frames_of(source, every: int, limit: int) -> list:
    frames = []
    for i in range(0, len(source), every):
        frame = source[i]
        frame.T_W_S_gt = orthonormalize(frame.T_W_S_gt)
        frames.append(frame)
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
    from scipy.spatial import cKDTree

    from slam.evaluation.metrics.mesh import surface_distances

    acc_pts = points[np.random.default_rng(1).choice(len(points), min(len(points), 100_000))]
    acc = surface_distances(acc_pts, gt)
    comp, _ = cKDTree(points).query(gt_samples, workers=-1)
    return float(acc.mean()), float(comp.mean()), float((comp < THRESHOLD_M).mean())


def scene_metrics(mesh, gt, gt_samples: np.ndarray) -> tuple[float, float, float]:
    import trimesh

    from slam.evaluation.metrics.mesh import surface_distances

    if len(mesh.faces) == 0:
        return float("inf"), float("inf"), 0.0
    pred_pts, _ = trimesh.sample.sample_surface(mesh, 100_000, seed=0)
    acc = surface_distances(pred_pts, gt)
    comp = surface_distances(gt_samples, mesh)
    return float(acc.mean()), float(comp.mean()), float((comp < THRESHOLD_M).mean())


def _repeated(build_and_extract) -> tuple:
    """``build_and_extract()`` (a map, its memory, build and extraction seconds) ``REPEATS``
    times: the first map and memory, the seconds as :class:`Timing` values."""
    runs = [build_and_extract() for _ in range(REPEATS)]
    return (*runs[0][:2], *(Timing(run[k] for run in runs) for k in (2, 3)))


def evaluate_scene(name: str, frames: list, gt, models, lines: list[str], note: str) -> None:
    import trimesh

    from slam.evaluation.metrics.mesh import visible_face_mask

    results: list[SceneResult] = []
    tsdf_points = {}
    for voxel in (0.025, 0.1):
        pts, mem, build, extract = _repeated(lambda voxel=voxel: tsdf(frames, voxel, 1_000_000))
        tsdf_points[voxel] = pts
        results.append(SceneResult(f"TSDF {voxel * 100:g} cm", 0, 0, 0, mem, build, extract))
    reference_is_tsdf = gt is None
    if reference_is_tsdf:
        ref_pts = tsdf_points[0.025]
        gt = trimesh.PointCloud(ref_pts)
        rng = np.random.default_rng(2)
        gt_samples = ref_pts[rng.choice(len(ref_pts), min(len(ref_pts), 100_000), replace=False)]
    else:
        intr = frames[0].intrinsics
        poses = np.stack([f.T_W_S_gt for f in frames])
        mask = visible_face_mask(gt, poses, intr.K, intr.width, intr.height)
        gt_samples, _ = trimesh.sample.sample_surface(
            gt, 100_000, face_weight=gt.area_faces * mask, seed=3
        )
    ours = []
    for label, model in models:
        log.info("%s: neural map with %s", name, label)
        mesh, mem, build, extract = _repeated(lambda model=model: run_ours(model, frames))
        ours.append((f"ours, {label}, V = {VOXEL_M * 100:g} cm", mesh, mem, build, extract))
    rows = []
    for res in results:
        voxel = 0.025 if "2.5" in res.method else 0.1
        if reference_is_tsdf and voxel == 0.025:
            rows.append((res, "(reference)"))
            continue
        pts = tsdf_points[voxel]
        if reference_is_tsdf:
            acc, comp, ratio = _pointcloud_only_metrics(pts, gt_samples)
        else:
            acc, comp, ratio = points_metrics(pts, gt, gt_samples)
        res.accuracy_m, res.completion_m, res.ratio = acc, comp, ratio
        rows.append((res, ""))
    for method, mesh, mem, build, extract in ours:
        if reference_is_tsdf:
            sample = (
                trimesh.sample.sample_surface(mesh, 200_000, seed=0)[0] if len(mesh.faces) else None
            )
            acc, comp, ratio = (
                _pointcloud_only_metrics(sample, gt_samples)
                if sample is not None
                else (float("inf"), float("inf"), 0.0)
            )
        else:
            acc, comp, ratio = scene_metrics(mesh, gt, gt_samples)
        rows.append((SceneResult(method, acc, comp, ratio, mem, build, extract), ""))
    lines += [f"#### {name}", "", note, ""]
    lines += [
        "| method | accuracy (cm) | completion (cm) | completion ratio < 5 cm | map memory (MB) | "
        "integrate (s) | surface extraction (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for res, tag in rows:
        if tag:
            metrics = f"{tag} | {tag} | {tag}"
        else:
            metrics = (
                f"{100 * res.accuracy_m:.2f} | {100 * res.completion_m:.2f} | "
                f"{100 * res.ratio:.1f} %"
            )
        lines.append(
            f"| {res.method} | {metrics} | {res.memory_bytes / 1e6:.2f} | {res.build_s:.1f} | "
            f"{res.extract_s:.1f} |"
        )
    lines.append("")


def _pointcloud_only_metrics(points: np.ndarray, ref: np.ndarray) -> tuple[float, float, float]:
    """Against a reference point set (no mesh): nearest-point distances both ways."""
    from scipy.spatial import cKDTree

    sub = points[np.random.default_rng(1).choice(len(points), min(len(points), 100_000))]
    acc, _ = cKDTree(ref).query(sub, workers=-1)
    comp, _ = cKDTree(points).query(ref, workers=-1)
    return float(acc.mean()), float(comp.mean()), float((comp < THRESHOLD_M).mean())


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
        repeats_line("Each map is built and extracted that often; the accuracy is the first's "
                     "(the same in every run)."),
        "",
    ]
    scenes = []
    try:
        # the demo's sequence (configs/demo.yaml), so the cached copy is reused
        src = make_source(
            "generated",
            kind="rgbd",
            num_frames=240,
            width=320,
            height=240,
            loader_options={"depth_options": {"stride": 2, "max_depth_m": 6.0}},
        )
        frames = _frames_of(src, 24 if quick else 8, 30)
        note = (
            "generated room; completion is over every ground-truth face inside some camera "
            "frustum, occluded ones included, so it is high for every method"
        )
        scenes.append(("Generated RGB-D room", frames, trimesh.load(src.gt_mesh_path), note))
    except Exception as exc:  # report, do not stop the other scenes
        lines += [f"Generated room skipped: {exc.__class__.__name__}: {exc}", ""]
    replica = DATA / "replica"
    if quick:
        lines += ["Quick mode: the generated room only (no Replica, no 7-Scenes).", ""]
    elif replica.is_dir():
        src = make_source(
            "replica", root=replica, sequence="office0", depth_options={"stride": stride}
        )
        gt = trimesh.load(replica / "office0_mesh.ply")
        frames = _frames_of(src, 1, 4)
        scenes.append(("Replica office0 (4 frames)", frames, gt, "real data"))
    else:
        lines += [f"Replica skipped: {replica} not found.", ""]
    kitchen = DATA / "7scenes_redkitchen"
    if quick:
        pass
    elif kitchen.is_dir():
        src = make_source(
            "7scenes", root=kitchen, sequence="seq-01", depth_options={"stride": stride}
        )
        frames = _frames_of(src, 40 if quick else 8, 10 if quick else 50)
        scenes.append(("7-Scenes redkitchen", frames, None, "real data, no GT mesh"))
    else:
        lines += [f"7-Scenes skipped: {kitchen} not found.", ""]
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


# ---------------------------------------------------------------------------- main
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer patches and frames")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    parser.add_argument("--weights", type=Path, default=DEFAULT_WEIGHTS, help="prior weights")
    parser.add_argument("--no-scenes", action="store_true", help="only the patch sections")
    parser.add_argument("--out", type=Path, default=RESULTS, help="Markdown section to write")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(args.threads)
    models = load_models(args.weights)
    shipped = models[0][1] if args.weights.is_file() else None
    meta = getattr(shipped, "metadata", {}) if shipped is not None else {}
    cmd = shlex.join(
        ["python", "-m", "benchmarks.bench_prior", *(sys.argv[1:] if argv is None else argv)]
    )
    lines = [
        *section_header(
            "Learned prior (mapping/training/patches.py, mapping/training/train.py)", cmd
        ),
        f"- torch threads: {torch.get_num_threads()}, CPU only",
        f"- Weights: `{args.weights}`"
        + (
            f" (identity {shipped.identity()}, {meta.get('steps')} steps, "
            f"{meta.get('train_wall_s')} s of training)"
            if shipped is not None
            else " (not found)"
        ),
        "",
    ]
    sets = heldout(32 if args.quick else 256)
    patch_section(models, sets, lines)
    lattice_section(models, sets, lines)
    if not args.no_scenes:
        scene_models = [m for m in models if not m[0].startswith("random")]
        if args.quick:
            scene_models = scene_models[:1]
        scenes_section(scene_models, args.quick, lines)
    write_text_atomic(args.out, "\n".join(lines) + "\n")
    log.info("wrote %s", args.out)


if __name__ == "__main__":
    main()
