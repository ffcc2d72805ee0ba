"""Rerun recording size and logging overhead of whole runs -> ``benchmarks/results/rerun.md``.

    python -m benchmarks.bench_rerun [--quick] [--frames A:B]
    python -m benchmarks.bench_rerun --rates [--before DIR] [--repeats 3]

Each case is run twice in this process with ``slam.app.runner``'s own ``execute``: once with
``--no-viz``
(:class:`~slam.algorithm.viz.NullLogger`) and once writing an ``.rrd`` file, after the sequence has
been
generated/cached so that neither run pays for generation. Measured:

- wall time of both runs and their difference (the end-to-end overhead, noisy on a shared machine);
- time spent inside the logger's methods (the logger is wrapped by a timer; this is the part of
  the overhead that Rerun logging itself costs, and it is much less noisy);
- time of the pipeline's ``map_logging`` stage, which also extracts meshes for the viewer at
  submap boundaries (only when a recording is made);
- the recording's size, its largest entities, and whether both runs wrote identical poses.

``--rates`` measures instead what the recording costs the pipeline: ``python -m slam.run`` as
a child process, with the default recording and with ``--no-viz``, on the demo (240 frames) and
the first 120 frames of the generated street (without the mesh scores and files, which come
after the pipeline), ``--repeats`` times each (interleaved, so that the
load of a shared machine falls on both alike), and reports the pipeline rate (frames/s,
``timing.frames_per_s`` of ``metrics.json``) as median, min and max. With ``--before DIR`` (a
checkout of another commit with its own ``.venv`` or this one's) the same runs are made there too,
for a before/after table (``benchmarks/results/rerun_rates.md``).

Quick mode: the first 60 frames of the demo. Full mode: the whole demo and, when
``../shared/data/kitti`` is present, a 1,500-frame LiDAR sequence generated along the real KITTI 00
trajectory.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.harness.machine import section_header
from benchmarks.harness.paths import DATA, RESULTS_DIR
from benchmarks.harness.paths import WORK_DIR as BENCH_OUT
from common.atomic_io import write_text_atomic

RESULTS = RESULTS_DIR / "rerun.md"
RATES = RESULTS_DIR / "rerun_rates.md"
RATE_CASES = {
    "demo (240 frames)": ["demo"],
    "generated street (120 frames)": ["generated-lidar", "--frames", "0:120"],
}
RATE_OUTPUTS = [
    *("--set", "output.mesh_samples=0", "--set", "output.write_map=false"),
    *("--set", "output.write_mesh=false"),
]
"""The rate runs skip what comes after the pipeline (mesh scores, map file, mesh file)."""
RATE_MODES = {"recording": [], "--no-viz": ["--no-viz"]}
WORK_DIR = BENCH_OUT / "rerun"
SHARED_KITTI = DATA / "kitti"


@dataclass
class Case:
    """One ``slam.app.runner`` command line (without viz flags)."""

    name: str
    argv: list[str]


@dataclass
class TimedCalls:
    """Seconds spent per logger method."""

    seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    calls: dict[str, int] = field(default_factory=lambda: defaultdict(int))

    @property
    def total_s(self) -> float:
        return float(sum(self.seconds.values()))


def timed_logger(inner, timings: TimedCalls):
    """A :class:`~slam.algorithm.viz.Logger` forwarding to ``inner`` and timing every call."""
    from slam.algorithm.viz import Logger

    class TimedLogger(Logger):
        def _call(self, name: str, *args: Any, **kwargs: Any) -> None:
            start = time.perf_counter()
            getattr(inner, name)(*args, **kwargs)
            timings.seconds[name] += time.perf_counter() - start
            timings.calls[name] += 1

        def set_time(self, frame_index, timestamp_s):
            self._call("set_time", frame_index, timestamp_s)

        def log_scan(self, points_W, colors=None):
            self._call("log_scan", points_W, colors)

        def log_sensor(self, T_W_S, intrinsics=None, rgb=None, depth_m=None):
            self._call("log_sensor", T_W_S, intrinsics, rgb, depth_m)

        def log_trajectory(self, name, positions_W):
            self._call("log_trajectory", name, positions_W)

        def log_loop_closures(self, accepted, rejected=()):
            self._call("log_loop_closures", accepted, rejected)

        def log_map(self, voxel_centers_W, voxel_values, mesh=None):
            self._call("log_map", voxel_centers_W, voxel_values, mesh)

        def log_metrics(self, **scalars):
            self._call("log_metrics", **scalars)

        def close(self):
            self._call("close")

    return TimedLogger()


def run_case(argv: list[str], folder: Path, timings: TimedCalls | None) -> dict[str, Any]:
    """``slam.app.runner.execute`` in this process; with ``timings``, the logger is wrapped by a
    timer."""
    import slam.app.recorder as recorder
    from slam.app.cli import build_parser, resolve_config
    from slam.app.runner import execute

    args = build_parser().parse_args(argv)
    entry, cfg = resolve_config(args)
    original = recorder.build_logger
    if timings is not None:
        recorder.build_logger = lambda *a, **k: timed_logger(original(*a, **k), timings)
    try:
        return execute(entry, cfg, folder, progress=False)
    finally:
        recorder.build_logger = original


def prepare(argv: list[str]) -> int:
    """Generate/cache the case's sequence; returns its number of frames."""
    from slam.app.cli import build_parser, resolve_config
    from slam.assembly.builders import build_source

    _, cfg = resolve_config(build_parser().parse_args([*argv, "--no-viz"]))
    return len(build_source(cfg))


def logger_alone(argv: list[str], submap_frames: int = 20) -> dict[str, Any]:
    """Drive :class:`RerunLogger` with a case's real frames at their ground-truth poses, without
    the pipeline: the logger's own cost and recording size, independent of the SLAM code. Every
    ``submap_frames`` frames, a map is logged: voxel centres of the ground-truth surface seen so
    far and the ground-truth mesh cropped to them (a stand-in of the same size class)."""
    import trimesh
    from scipy.spatial import cKDTree

    from slam.app.cli import build_parser, resolve_config
    from slam.app.rerun_logger import RerunLogger
    from slam.assembly.builders import build_source

    _, cfg = resolve_config(build_parser().parse_args([*argv, "--no-viz"]))
    source = build_source(cfg)
    voxel = cfg.mapping.voxel_size_m
    gt_mesh = trimesh.load(source.gt_mesh_path, force="mesh") if source.gt_mesh_path else None
    path = WORK_DIR / "logger_alone.rrd"
    path.unlink(missing_ok=True)
    timings = TimedCalls()
    logger = timed_logger(RerunLogger(rrd_path=path, voxel_size_m=voxel, up_axis="+z"), timings)
    positions: list[np.ndarray] = []
    seen: set[tuple[int, int, int]] = set()
    load_s = 0.0
    for i in range(len(source)):
        start = time.perf_counter()
        frame = source[i]
        load_s += time.perf_counter() - start
        T = np.asarray(frame.T_W_S_gt)
        points_W = frame.points @ T[:3, :3].T + T[:3, 3]
        positions.append(T[:3, 3])
        seen.update(map(tuple, np.floor(points_W[::10] / voxel).astype(int)))
        logger.set_time(i, frame.timestamp)
        logger.log_scan(points_W, frame.colors)
        logger.log_sensor(T, frame.intrinsics, frame.rgb, frame.depth)
        for name in ("odometry", "optimized", "gt"):
            logger.log_trajectory(name, np.asarray(positions))
        logger.log_metrics(frame_ms=1.0, odometry_ms=1.0, submaps=i // submap_frames, loops=0)
        if (i + 1) % submap_frames == 0 and gt_mesh is not None:
            centers = (np.array(sorted(seen)) + 0.5) * voxel
            near = cKDTree(centers).query(gt_mesh.triangles_center, distance_upper_bound=voxel)[0]
            mesh = gt_mesh.submesh([np.flatnonzero(np.isfinite(near))], append=True)
            logger.log_map(centers, np.ones(len(centers)), mesh)
    logger.close()
    return {
        "frames": len(source),
        "logger_s": timings.total_s,
        "logger_by_method": dict(timings.seconds),
        "calls_by_method": dict(timings.calls),
        "load_s": load_s,
        "rrd_bytes": path.stat().st_size,
    }


def same_poses(a: Path, b: Path) -> bool:
    names = ("poses_odometry.kitti.txt", "poses_slam.kitti.txt")
    return all((a / n).read_bytes() == (b / n).read_bytes() for n in names)


def measure(case: Case) -> dict[str, Any]:
    from slam.app.rerun_logger import summarize_recording

    folder = WORK_DIR / case.name
    shutil.rmtree(folder, ignore_errors=True)
    frames = prepare(case.argv)
    plain = run_case([*case.argv, "--no-viz", "--no-progress"], folder / "no-viz", None)
    timings = TimedCalls()
    rrd = folder / "rrd" / "recording.rrd"
    logged = run_case([*case.argv, "--rrd", str(rrd), "--no-progress"], folder / "rrd", timings)
    summary = summarize_recording(rrd)
    stages_plain = plain["timing"]["stages"]
    stages_logged = logged["timing"]["stages"]
    map_logging_s = stages_logged.get("map_logging", {}).get("total_s", 0.0)
    return {
        "name": case.name,
        "command": "python -m slam.run " + " ".join(case.argv) + " [--no-viz | --rrd FILE]",
        "frames": frames,
        "wall_plain_s": plain["timing"]["wall_s"],
        "wall_logged_s": logged["timing"]["wall_s"],
        "map_logging_plain_s": stages_plain.get("map_logging", {}).get("total_s", 0.0),
        "map_logging_logged_s": map_logging_s,
        "logger_s": timings.total_s,
        "logger_by_method": dict(timings.seconds),
        "calls_by_method": dict(timings.calls),
        "rrd_bytes": summary.size_bytes,
        "entities": summary.entities,
        "same_poses": same_poses(folder / "no-viz", folder / "rrd"),
    }


def _method_table(result: dict) -> list[str]:
    """Markdown table of the time spent in each logger method, slowest first."""
    lines = ["| method | calls | total [s] | per call [ms] |", "|---|---:|---:|---:|"]
    for method, seconds in sorted(result["logger_by_method"].items(), key=lambda kv: -kv[1]):
        calls = result["calls_by_method"][method]
        lines.append(f"| {method} | {calls} | {seconds:.3f} | {1e3 * seconds / calls:.2f} |")
    return lines


def markdown(results: list[dict[str, Any]], alone: dict[str, Any], command: str) -> str:
    lines = [
        *section_header("rerun", command),
        "",
        "Rerun recording size and logging overhead of whole runs (`benchmarks/bench_rerun.py`).",
        "",
        "- Each case ran twice in one process (slam.app.runner's `execute`): "
        "`--no-viz` (NullLogger) "
        "first, then `--rrd`; the sequence was generated beforehand. Wall times on a shared "
        "machine are noisy; the time inside the logger is measured directly.",
        "- `map_logging` is the pipeline's stage that hands the map to the logger; with a "
        "recording it also extracts the mesh every `viz.mesh_every_submaps` submaps for the "
        "viewer (with `--no-viz` only the final mesh), so its growth is visualisation cost "
        "paid by the pipeline, not by Rerun.",
        "",
        "| case | frames | wall no-viz [s] | wall rrd [s] | wall diff | time in logger [s] "
        "| logger / wall rrd | map_logging stage no-viz / rrd [s] | recording [MB] "
        "| MB / 100 frames | identical poses |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in results:
        diff = r["wall_logged_s"] - r["wall_plain_s"]
        lines.append(
            f"| {r['name']} | {r['frames']} | {r['wall_plain_s']:.1f} | {r['wall_logged_s']:.1f} "
            f"| {diff:+.1f} s ({100 * diff / r['wall_plain_s']:+.1f} %) | {r['logger_s']:.2f} "
            f"| {100 * r['logger_s'] / r['wall_logged_s']:.1f} % "
            f"| {r['map_logging_plain_s']:.1f} / {r['map_logging_logged_s']:.1f} "
            f"| {r['rrd_bytes'] / 1e6:.1f} | {100 * r['rrd_bytes'] / 1e6 / r['frames']:.1f} "
            f"| {'yes' if r['same_poses'] else 'NO'} |"
        )
    lines += [
        "",
        f"### Logger alone on the demo's {alone['frames']} real frames",
        "",
        "RerunLogger driven directly with the generated demo frames at their ground-truth poses "
        "(scan, RGB-D images, three growing trajectories, metrics every frame; every 20 frames "
        "a map: voxel centres of the surface seen so far and the ground-truth mesh near them). "
        "No SLAM work: this is the cost of logging alone.",
        "",
        f"- Recording: {alone['rrd_bytes'] / 1e6:.1f} MB "
        f"({100 * alone['rrd_bytes'] / 1e6 / alone['frames']:.1f} MB per 100 frames)",
        f"- Time inside the logger: {alone['logger_s']:.2f} s "
        f"({1e3 * alone['logger_s'] / alone['frames']:.1f} ms per frame); reading the frames "
        f"took {alone['load_s']:.2f} s",
        "",
        *_method_table(alone),
    ]
    for r in results:
        lines += [
            "",
            f"### {r['name']}: time inside the logger per method",
            "",
            f"Command: `{r['command']}`",
            "",
            *_method_table(r),
        ]
        lines += [
            "",
            f"Largest entities of the recording (uncompressed Arrow bytes; the file is "
            f"{r['rrd_bytes'] / 1e6:.1f} MB):",
            "",
            "| entity | rows | MB |",
            "|---|---:|---:|",
        ]
        top = sorted(r["entities"].items(), key=lambda kv: -kv[1].arrow_bytes)[:8]
        for entity, stats in top:
            rows = stats.rows + stats.static_rows
            lines.append(f"| {entity} | {rows} | {stats.arrow_bytes / 1e6:.2f} |")
    return "\n".join(lines) + "\n"


def pipeline_rate(tree: Path, argv: list[str], folder: Path) -> float:
    """Frames/s of one ``python -m slam.run`` in ``tree`` (a child process)."""
    shutil.rmtree(folder, ignore_errors=True)
    python = tree / ".venv" / "bin" / "python"
    command = [str(python if python.exists() else sys.executable), "-m", "slam.run", *argv]
    command += ["--out", str(folder), "--no-progress"]
    subprocess.run(command, cwd=tree, check=True, stdout=subprocess.DEVNULL)
    metrics = json.loads((folder / "metrics.json").read_text())
    shutil.rmtree(folder, ignore_errors=True)
    return float(metrics["timing"]["frames_per_s"])


def measure_rates(trees: dict[str, Path], repeats: int) -> dict[tuple[str, str, str], list]:
    """``{(tree, case, mode): [frames/s per repeat]}``, the repeats interleaved."""
    rates: dict[tuple[str, str, str], list[float]] = defaultdict(list)
    for repeat in range(repeats):
        for case, argv in RATE_CASES.items():
            for tree, root in trees.items():
                for mode, flags in RATE_MODES.items():
                    run = [*argv, *flags, *RATE_OUTPUTS]
                    rate = pipeline_rate(root, run, WORK_DIR / "rates")
                    rates[(tree, case, mode)].append(rate)
                    line = f"{tree} | {case} | {mode} | run {repeat + 1}: {rate:.2f} frames/s"
                    print(f"bench_rerun: {line}", file=sys.stderr, flush=True)
    return rates


def rates_markdown(rates: dict, trees: dict[str, Path], repeats: int, command: str) -> str:
    def cell(values: list[float]) -> str:
        return f"{statistics.median(values):.1f} ({min(values):.1f}-{max(values):.1f})"

    lines = [
        *section_header("rerun rates", command),
        "",
        "Pipeline rate (frames/s from the first frame read to the end of the final optimisation,"
        f" `timing.frames_per_s`) of `python -m slam.run`: median of {repeats} runs (min-max), "
        "with the default recording (`recording.rrd`) and with `--no-viz`.",
        "",
        "| code | case | recording [frames/s] | --no-viz [frames/s] | recording / --no-viz |",
        "|---|---|---:|---:|---:|",
    ]
    for tree in trees:
        for case in RATE_CASES:
            logged, plain = rates[(tree, case, "recording")], rates[(tree, case, "--no-viz")]
            ratio = statistics.median(logged) / statistics.median(plain)
            lines.append(f"| {tree} | {case} | {cell(logged)} | {cell(plain)} | {ratio:.2f} |")
    return "\n".join(lines) + "\n"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="first 30 demo frames only")
    parser.add_argument("--frames", help="frame range of the demo case (overrides the mode)")
    parser.add_argument(
        "--skip-lidar", action="store_true", help="full mode without the 1,500-frame LiDAR case"
    )
    parser.add_argument(
        "--rates", action="store_true", help="pipeline rate with recording vs --no-viz instead"
    )
    parser.add_argument(
        "--before", type=Path, help="--rates: also measure this checkout (e.g. a git worktree)"
    )
    parser.add_argument("--repeats", type=int, default=3, help="--rates: runs of each case")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    argv_shown = list(sys.argv[1:] if argv is None else argv)
    command = " ".join(["python -m benchmarks.bench_rerun", *argv_shown])
    if args.rates:
        here = Path(__file__).resolve().parents[1]
        trees = {"before": args.before.resolve()} if args.before else {}
        trees["this checkout"] = here
        rates = measure_rates(trees, args.repeats)
        write_text_atomic(RATES, rates_markdown(rates, trees, args.repeats, command))
        print(f"bench_rerun: wrote {RATES}", file=sys.stderr)
        return 0

    frames = args.frames or ("0:30" if args.quick else None)
    demo = ["demo", *(["--frames", frames] if frames else [])]
    cases = [Case("demo" + (f" [{frames}]" if frames else ""), demo)]
    if not args.quick and not args.skip_lidar:
        if SHARED_KITTI.is_dir():
            cases.append(
                Case(
                    "generated LiDAR, KITTI 00 trajectory",
                    [
                        "generated-lidar",
                        "--set",
                        "generated.trajectory=kitti",
                        "--set",
                        f"generated.kitti_poses={SHARED_KITTI / 'poses' / '00.txt'}",
                        "--set",
                        f"generated.kitti_calib={SHARED_KITTI / 'sequences' / '00' / 'calib.txt'}",
                        "--set",
                        "generated.num_frames=1500",
                    ],
                )
            )
        else:
            print(f"skipping the KITTI-trajectory case: {SHARED_KITTI} is absent", file=sys.stderr)
    print("bench_rerun: logger alone on the demo frames", file=sys.stderr)
    alone = logger_alone(["demo"])
    results = []
    for case in cases:
        print(f"bench_rerun: {case.name}", file=sys.stderr)
        results.append(measure(case))
    write_text_atomic(RESULTS, markdown(results, alone, command))
    print(f"bench_rerun: wrote {RESULTS}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
