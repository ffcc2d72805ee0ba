"""LiDAR map quality: the neural map against a LiDAR TSDF, over the surface the scans observed.

    python -m benchmarks.bench_lidar_map [--quick | --full] [--set KEY=VALUE ...]
        [--before-set KEY=VALUE ...] [--variant NAME KEY=VALUE ...] [--street NAME] [--no-mulran]
        [--jobs N] [--out FILE.md]

The generated street along KITTI 00 (``benchmarks.harness.kitti``) with configs/kitti.yaml, run
with ground-truth poses (mapping only) and as SLAM (KISS-ICP, loops, remapping). Each final mesh is
scored against the street's ground-truth mesh after the SE(3) alignment ``slam.eval`` uses:
globally and, for SLAM, per stretch of scans with the stretch's own alignment. Beside each: a LiDAR
TSDF (``benchmarks.harness.lidar_tsdf``) of the same scans at the same poses. Scores
(``benchmarks.harness.lidar_surface``): precision, recall and F-score at 10 and 20 cm, accuracy and
completion, over the ground-truth surface observed within 30 m and within :data:`SENSOR_RANGE_M`.
Cost: pipeline wall time, mesh extraction, ``map.npz`` bytes, map memory and the run's own peak
RSS. ``--before-set`` runs the neural map again with those overrides as the "before" rows (default
:data:`BEFORE_SETS`); ``--variant`` adds rows of another configuration; ``--street`` takes another
of the generated street's data variants. Real scans: the MulRan Riverside02 keyframes with
configs/lidar.yaml and their reference poses, scored by precision against the placed scan points
only (recall would score their sparsity).

``--quick``: the first :data:`QUICK_SCANS` scans of the quick window, :data:`QUICK_MULRAN`
MulRan keyframes; ``--full`` (the default): all 4,541 scans, every keyframe. Writes
benchmarks/results/lidar_map.md (and .json) and lidar_map_corner.png (one street corner of the
pictured maps and the ground truth, ``benchmarks.lidar_map_picture``).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import itertools
import json
import logging
import multiprocessing
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.harness.child import in_child_measured
from benchmarks.harness.cli import command_line, start_logging
from benchmarks.harness.kitti import KITTI_POSES, STANDARD_STREET, STREETS, kitti_source
from benchmarks.harness.kitti import window as kitti_window
from benchmarks.harness.machine import section_header
from benchmarks.harness.paths import DATA, RESULTS_DIR
from benchmarks.harness.pipeline import add_override_arguments
from benchmarks.lidar_map_picture import PICTURED, corner_picture
from benchmarks.lidar_map_report import BEFORE_ROWS, report_lines
from common.atomic_io import write_text_atomic

log = logging.getLogger("benchmarks.bench_lidar_map")

QUICK_SCANS = 150
QUICK_STRETCH_SCANS = 75
FULL_STRETCH_SCANS = 600
QUICK_MULRAN = 40
RANGE_LIMITS_M = (30.0, 80.0)
SENSOR_RANGE_M = 80.0
"""The range the maps are scored to, and the TSDF's integration range."""
BEFORE_SETS = ["submaps.max_range_m=30"]
"""The 'before' rows without ``--before-set``: the map cut at 30 m, as it was before it reached
the sensor's range."""
TSDF_VOXEL_M = 0.2
OBSERVED_CHUNK_SCANS = 50
"""Scans whose points are held at once to find the observed surface (memory, full mode)."""
MULRAN = DATA / "mulran_riverside02_keyframes"


# ---------------------------------------------------------------------------- child processes
def _mesh_arrays(mesh) -> dict[str, np.ndarray]:
    return {"vertices": np.asarray(mesh.vertices), "faces": np.asarray(mesh.faces)}


def _neural_map(cfg, source) -> dict[str, Any]:
    """One run of the pipeline on ``source``: its poses, mesh and costs."""
    from benchmarks.harness.pipeline import run_pipeline
    from mapping.map_io import save_map

    pipeline, wall = run_pipeline(cfg, source)
    start = time.perf_counter()
    mesh = pipeline.map.extract_mesh()
    mesh_s = time.perf_counter() - start
    with tempfile.TemporaryDirectory(prefix="lidar-map-") as work:
        path = Path(work) / "map.npz"
        save_map(pipeline.map, path, list(pipeline.submaps.values()))
        file_bytes = path.stat().st_size
    return {
        **_mesh_arrays(mesh),
        "poses": pipeline.slam_poses(),
        "wall_s": wall,
        "mesh_s": mesh_s,
        "map_file_bytes": file_bytes,
        "map_memory_bytes": int(pipeline.map.memory_bytes()),
        "submaps": len(pipeline.submaps),
        "loops_kept": sum(1 for c in pipeline.accepted_loops() if c.graph_inlier),
    }


def street_config(odometry: str, sets: list[str]):
    """configs/kitti.yaml with ``odometry`` and the overrides ``sets``."""
    from benchmarks.harness.pipeline import load_config
    from slam.assembly.config import merge_overrides, set_overrides

    street = {"source": {"dataset": "generated"}, "odometry": {"method": odometry}}
    return load_config("kitti", merge_overrides(street, set_overrides(sets)))


def street_run(
    quick: bool, frames: int | None, odometry: str, sets: list[str], street: dict[str, Any]
) -> dict:
    return _neural_map(street_config(odometry, sets), kitti_source(quick, frames, **street))


def tsdf_map(scans, poses: np.ndarray) -> dict[str, Any]:
    """The TSDF of ``scans`` (an iterable of sensor-frame points) at ``poses``."""
    from benchmarks.harness.lidar_tsdf import LidarTsdf

    tsdf = LidarTsdf(TSDF_VOXEL_M)
    start = time.perf_counter()
    for points, T in zip(scans, poses, strict=True):
        tsdf.integrate(points[np.linalg.norm(points, axis=1) <= SENSOR_RANGE_M], T)
    tsdf.flush()  # the last batch belongs to the integration time
    wall = time.perf_counter() - start
    start = time.perf_counter()
    mesh = tsdf.extract_mesh()
    return {
        **_mesh_arrays(mesh),
        "wall_s": wall,
        "mesh_s": time.perf_counter() - start,
        "map_memory_bytes": tsdf.memory_bytes(),
        "voxels": tsdf.num_voxels,
    }


def street_tsdf(quick: bool, frames: int | None, poses: np.ndarray, street: dict[str, Any]) -> dict:
    source = kitti_source(quick, frames, **street)
    return tsdf_map((frame.points for frame in source), poses)


def _mulran_config(frames: int | None, sets: list[str]):
    from benchmarks.harness.pipeline import load_config
    from slam.assembly.builders import build_source
    from slam.assembly.config import merge_overrides, set_overrides
    from slam.assembly.lidar_scale import scale_config

    overrides = {
        "source": {
            "dataset": "lidar",
            "root": str(MULRAN / "scans"),
            "lidar": {"gt_poses": str(MULRAN / "optimized_poses.txt")},
            **({"frames": f"0:{frames}"} if frames else {}),
        },
        "odometry": {"method": "gt"},
    }
    cfg = load_config("lidar", merge_overrides(overrides, set_overrides(sets)))
    source = build_source(cfg)
    scale_config(cfg, source[0].points)
    return cfg, source


def mulran_run(frames: int | None, sets: list[str]) -> dict:
    return _neural_map(*_mulran_config(frames, sets))


def mulran_tsdf(frames: int | None) -> dict:
    _, source = _mulran_config(frames, [])
    return tsdf_map((frame.points for frame in source), source.gt_poses)


def measured(fn, *args) -> dict:
    """``fn(*args)`` in a child process, with its peak RSS and wall time."""
    result, usage = in_child_measured(fn, *args)
    return {**result, "peak_rss_mb": usage.peak_rss_mb, "process_s": usage.wall_s}


# ---------------------------------------------------------------------------- scoring
def _mesh(result: dict, T: np.ndarray | None = None):
    import trimesh

    mesh = trimesh.Trimesh(result["vertices"], result["faces"], process=False)
    if T is not None:
        mesh.apply_transform(T)
    return mesh


def stretches(num_scans: int, length: int) -> list[tuple[int, int]]:
    """``[start, end)`` of consecutive stretches of ``length`` scans (the last one may be
    shorter, but not under half of ``length``: then it joins the one before)."""
    bounds = [*range(0, num_scans, length), num_scans]
    if len(bounds) > 2 and bounds[-1] - bounds[-2] < length // 2:
        bounds.pop(-2)
    return list(itertools.pairwise(bounds))


class StreetScorer:
    """The street's ground truth and the surface its scans observed, per stretch and range."""

    def __init__(
        self, quick: bool, frames: int | None, stretch_scans: int, street: dict[str, Any]
    ) -> None:
        import trimesh

        from benchmarks.harness.lidar_surface import (
            REGION_MARGIN_M,
            crop_to_region,
            gt_samples,
            observed_mask,
            scan_set,
        )

        source = kitti_source(quick, frames, **street)
        self.gt_poses = np.asarray(source.gt_poses)
        positions = self.gt_poses[:, :3, 3]
        gt = trimesh.load(source.gt_mesh_path, force="mesh", process=False)
        self.gt_region = crop_to_region(gt, positions, SENSOR_RANGE_M + REGION_MARGIN_M)
        samples = gt_samples(self.gt_region)
        self.stretches = stretches(len(self.gt_poses), stretch_scans)
        masks: dict[tuple[int, int, float], np.ndarray] = {}
        for first, end in self.stretches:
            # a few scans at a time: a sample is observed by the stretch when some chunk saw it
            for start in range(first, end, OBSERVED_CHUNK_SCANS):
                chunk = range(start, min(start + OBSERVED_CHUNK_SCANS, end))
                scans = scan_set(
                    [source[i].points for i in chunk], self.gt_poses[chunk], SENSOR_RANGE_M
                )
                for limit in RANGE_LIMITS_M:
                    seen = observed_mask(samples, scans, limit)
                    key = (first, end, limit)
                    masks[key] = seen if key not in masks else masks[key] | seen
        for limit in RANGE_LIMITS_M:
            parts = [masks[(a, b, limit)] for a, b in self.stretches]
            masks[(0, len(self.gt_poses), limit)] = np.logical_or.reduce(parts)
        self.observed = {key: samples[mask] for key, mask in masks.items()}

    def score(self, result: dict, poses: np.ndarray, per_stretch: bool) -> list[dict]:
        """Rows of scores of one map (its poses ``poses``): global, then per stretch."""
        from benchmarks.harness.lidar_surface import region_scores
        from slam.evaluation.metrics.trajectory import align_se3

        regions = [("global", 0, len(self.gt_poses))]
        if per_stretch and len(self.stretches) > 1:
            regions += [(f"scans {a}-{b - 1}", a, b) for a, b in self.stretches]
        rows = []
        for name, first, end in regions:
            T = align_se3(poses[first:end], self.gt_poses[first:end])
            mesh = _mesh(result, T)
            for limit in RANGE_LIMITS_M:
                scores = region_scores(
                    mesh,
                    self.gt_region,
                    self.observed[(first, end, limit)],
                    self.gt_poses[first:end, :3, 3],
                    limit,
                )
                rows.append({"region": name, "range_m": limit, **scores})
        return rows


def mulran_scores(
    result: dict, run_poses: np.ndarray | None, frames: int | None, limits: list[float]
) -> list[dict]:
    """Precision of a MulRan map against the scan points placed by the reference poses. A run's
    mesh is in the frame its files claim, the first scan's, so it is carried into the reference
    poses' world by the first reference pose (no alignment); a TSDF built at the reference poses
    (``run_poses`` None) is already there."""
    from benchmarks.harness.lidar_surface import point_precision

    _, source = _mulran_config(frames, [])
    poses = np.asarray(source.gt_poses)
    points = np.concatenate(
        [frame.points @ T[:3, :3].T + T[:3, 3] for frame, T in zip(source, poses, strict=True)]
    )
    mesh = _mesh(result, None if run_poses is None else poses[0] @ np.linalg.inv(run_poses[0]))
    positions = poses[:, :3, 3]
    return [
        {"region": "global", "range_m": limit, **point_precision(mesh, points, positions, limit)}
        for limit in limits
    ]


def _scores(
    scorer: StreetScorer | None,
    kind: str,
    result: dict,
    poses: np.ndarray | None,
    mulran: tuple[int | None, list[float]],
) -> list[dict]:
    """The score rows of one map built at ``poses`` (run in a child process)."""
    if kind == "mulran":
        return mulran_scores(result, poses, *mulran)
    return scorer.score(result, poses, per_stretch=kind == "kiss-icp")


# ---------------------------------------------------------------------------- main
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument(
        "--quick",
        action="store_true",
        help=f"first {QUICK_SCANS} scans of the quick window, {QUICK_MULRAN} MulRan keyframes",
    )
    mode.add_argument("--full", action="store_true", help="all 4,541 scans (the default)")
    add_override_arguments(parser, "neural map's 'before' rows")
    parser.add_argument(
        "--variant",
        dest="variants",
        nargs="+",
        action="append",
        default=[],
        metavar=("NAME", "KEY=VALUE"),
        help="also run the neural map with these overrides, as rows 'neural map, NAME'",
    )
    parser.add_argument(
        "--street",
        choices=list(STREETS),
        default=STANDARD_STREET,
        help="the generated street (benchmarks/bench_variants.py's data variants)",
    )
    parser.add_argument("--no-mulran", action="store_true", help="skip the MulRan keyframes")
    parser.add_argument("--jobs", type=int, default=2, help="child processes at a time")
    parser.add_argument("--out", type=Path, default=RESULTS_DIR / "lidar_map.md")
    return parser


def _variants(args) -> dict[str, list[str]]:
    """Each neural-map row's name and its overrides: before, as configured, named variants."""
    before = args.before_sets or BEFORE_SETS
    variants = {BEFORE_ROWS: args.sets + before, "neural map": args.sets}
    for name, *sets in args.variants:
        variants[f"neural map, {name}"] = args.sets + sets
    return variants


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    start_logging("%(asctime)s %(name)s: %(message)s")
    if not KITTI_POSES.is_file():
        print(
            f"error: {KITTI_POSES}: missing; the street follows KITTI 00's poses", file=sys.stderr
        )
        return 2
    quick = args.quick
    frames = QUICK_SCANS if quick else None
    stretch_scans = QUICK_STRETCH_SCANS if quick else FULL_STRETCH_SCANS
    mulran_frames = QUICK_MULRAN if quick else None
    do_mulran = not args.no_mulran and (MULRAN / "scans").is_dir()
    command = command_line("bench_lidar_map", argv)
    variants = _variants(args)
    street = STREETS[args.street]
    started = time.perf_counter()
    context = multiprocessing.get_context("spawn")
    runs: dict[str, dict] = {}
    with concurrent.futures.ProcessPoolExecutor(args.jobs, mp_context=context) as pool:
        futures = {}
        for name, sets in variants.items():
            for odometry in ("gt", "kiss-icp"):
                futures[(name, odometry)] = pool.submit(
                    measured, street_run, quick, frames, odometry, sets, street
                )
            if do_mulran:
                futures[(name, "mulran")] = pool.submit(measured, mulran_run, mulran_frames, sets)
        scorer_future = pool.submit(StreetScorer, quick, frames, stretch_scans, street)
        gt_poses = np.asarray(kitti_source(quick, frames, **street).gt_poses)
        futures[("TSDF", "gt")] = pool.submit(
            measured, street_tsdf, quick, frames, gt_poses, street
        )
        if do_mulran:
            futures[("TSDF", "mulran")] = pool.submit(measured, mulran_tsdf, mulran_frames)
        slam = futures[("neural map", "kiss-icp")].result()
        futures[("TSDF", "kiss-icp")] = pool.submit(
            measured, street_tsdf, quick, frames, slam["poses"], street
        )
        for (name, kind), future in futures.items():
            runs.setdefault(kind, {})[name] = future.result()
            log.info("%s, %s: done", name, kind)
        scorer = scorer_future.result()
        mulran = (mulran_frames, list(RANGE_LIMITS_M))
        poses = {"gt": gt_poses, "kiss-icp": slam["poses"], "mulran": None}
        scores = {
            (kind, name): pool.submit(
                _scores, scorer, kind, result, result.get("poses", poses[kind]), mulran
            )
            for kind, by_name in runs.items()
            for name, result in by_name.items()
        }
        results: dict[str, Any] = {"command": command, "quick": quick, "runs": {}}
        for (kind, name), future in scores.items():
            cost = {k: v for k, v in runs[kind][name].items() if np.isscalar(v)}
            results["runs"].setdefault(kind, {})[name] = {"cost": cost, "scores": future.result()}
            log.info("scored %s, %s", name, kind)
    results["seconds"] = time.perf_counter() - started
    results["observed_samples"] = {
        f"{a}-{b}@{limit:g}": len(v) for (a, b, limit), v in scorer.observed.items()
    }
    picture = args.out.with_name(f"{args.out.stem}_corner.png")
    pictured = [name for name in PICTURED if name in variants]
    max_ranges_m = {n: street_config("gt", variants[n]).submaps.max_range_m for n in pictured}
    caption = corner_picture(picture, runs, scorer, max_ranges_m)
    log.info("wrote %s", picture)
    lines = section_header("LiDAR map quality (neural map vs TSDF)", command)
    lines += report_lines(
        results,
        window=kitti_window(quick).describe(frames)
        + ("" if args.street == STANDARD_STREET else f", street variant '{args.street}'"),
        mulran_frames=mulran_frames,
        stretch_scans=stretch_scans,
        variants=variants,
        sensor_range_m=SENSOR_RANGE_M,
        tsdf_voxel_m=TSDF_VOXEL_M,
    )
    lines += [f"![The street corner]({picture.name})", "", caption, ""]
    write_text_atomic(args.out.with_suffix(".json"), json.dumps(results, indent=2, default=float))
    write_text_atomic(args.out, "\n".join(lines) + "\n")
    log.info("wrote %s in %.0f s", args.out, results["seconds"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
