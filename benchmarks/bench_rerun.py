"""Rerun recording size, logging overhead and the pipeline rate a recording leaves ->
``benchmarks/results/rerun.md``.

    python -m benchmarks.bench_rerun [--quick] [--frames A:B] [--repeats 3]
    python -m benchmarks.bench_rerun --rates [--before DIR] [--repeats 3] [--kitti-root DIR]

Rates: the pipeline rate (``timing.frames_per_s``) of ``python -m slam.run`` child processes with
the default recording and with ``--no-viz``, on the demo and the first 120 frames of the
generated street, ``--repeats`` times interleaved. ``--rates`` measures only these; ``--before
DIR`` (another checkout) adds its rows, and ``--kitti-root DIR`` a case of every scan of the
KITTI-layout sequence 00 in DIR, such as the full-length generated street
(``benchmarks/results/rerun_rates.md``).

Overhead: each case runs twice in this process with ``slam.app.runner``'s ``execute`` (after its
sequence is generated): with ``--no-viz`` and writing an ``.rrd`` file. Measured: both wall times
and their difference (noisy on a shared machine); the time inside the logger's methods (the
logger wrapped by a timer); the pipeline's ``map_logging`` stage (it also meshes for the viewer);
the recording's size and largest entities; whether both runs wrote identical poses.

Quick mode: the overhead of the first 30 demo frames, without the per-method and per-entity
tables. Full mode: the whole demo and, when ``../shared/data/kitti`` is present, 1,500 LiDAR
frames generated along KITTI 00's trajectory.
"""

from __future__ import annotations

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

from benchmarks.harness.cli import bench_parser, command_line
from benchmarks.harness.machine import section_header
from benchmarks.harness.paths import DATA, RESULTS_DIR
from benchmarks.harness.paths import WORK_DIR as BENCH_OUT
from benchmarks.harness.results import table
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
class TimedCalls:
    """Seconds spent per logger method."""

    seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    calls: dict[str, int] = field(default_factory=lambda: defaultdict(int))

    @property
    def total_s(self) -> float:
        return float(sum(self.seconds.values()))

    def summary(self) -> dict[str, Any]:
        """The time inside the logger, in all and by method, and the calls by method."""
        return {
            "logger_s": self.total_s,
            "logger_by_method": dict(self.seconds),
            "calls_by_method": dict(self.calls),
        }


LOGGER_METHODS = (
    "set_time",
    "log_scan",
    "log_sensor",
    "log_trajectory",
    "log_loop_closures",
    "log_map",
    "log_metrics",
    "flush",
    "close",
)


def timed_logger(inner, timings: TimedCalls):
    """A :class:`~slam.algorithm.viz.Logger` forwarding to ``inner`` and timing every call."""
    from slam.algorithm.viz import Logger

    def forward(name: str):
        def call(self, *args: Any, **kwargs: Any) -> None:
            start = time.perf_counter()
            getattr(inner, name)(*args, **kwargs)
            timings.seconds[name] += time.perf_counter() - start
            timings.calls[name] += 1

        return call

    return type("TimedLogger", (Logger,), {name: forward(name) for name in LOGGER_METHODS})()


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


def prepare(argv: list[str]):
    """The case's run config and its source (generated or cached now)."""
    from slam.app.cli import build_parser, resolve_config
    from slam.assembly.builders import build_source

    _, cfg = resolve_config(build_parser().parse_args([*argv, "--no-viz"]))
    return cfg, build_source(cfg)


def logger_alone(argv: list[str], submap_frames: int = 20) -> dict[str, Any]:
    """Drive :class:`RerunLogger` with a case's real frames at their ground-truth poses, without
    the pipeline: the logger's own cost and recording size, independent of the SLAM code. Every
    ``submap_frames`` frames, a map is logged: voxel centres of the ground-truth surface seen so
    far and the ground-truth mesh cropped to them (a stand-in of the same size class)."""
    import trimesh
    from scipy.spatial import cKDTree

    from slam.app.rerun_logger import RerunLogger

    cfg, source = prepare(argv)
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
        **timings.summary(),
        "load_s": load_s,
        "rrd_bytes": path.stat().st_size,
    }


def same_poses(a: Path, b: Path) -> bool:
    names = ("poses_odometry.kitti.txt", "poses_slam.kitti.txt")
    return all((a / n).read_bytes() == (b / n).read_bytes() for n in names)


def measure(name: str, argv: list[str]) -> dict[str, Any]:
    """One case (a ``slam.run`` command line without viz flags) with ``--no-viz`` and with
    ``--rrd``."""
    from slam.app.rerun_logger import summarize_recording

    folder = WORK_DIR / name
    shutil.rmtree(folder, ignore_errors=True)
    frames = len(prepare(argv)[1])
    plain = run_case([*argv, "--no-viz", "--no-progress"], folder / "no-viz", None)
    timings = TimedCalls()
    rrd = folder / "rrd" / "recording.rrd"
    logged = run_case([*argv, "--rrd", str(rrd), "--no-progress"], folder / "rrd", timings)
    summary = summarize_recording(rrd)

    def map_logging_s(run: dict) -> float:
        return run["timing"]["stages"].get("map_logging", {}).get("total_s", 0.0)

    return {
        "name": name,
        "frames": frames,
        "command": "python -m slam.run " + " ".join(argv) + " [--no-viz | --rrd FILE]",
        "wall_plain_s": plain["timing"]["wall_s"],
        "wall_logged_s": logged["timing"]["wall_s"],
        "map_logging_plain_s": map_logging_s(plain),
        "map_logging_logged_s": map_logging_s(logged),
        **timings.summary(),
        "rrd_bytes": summary.size_bytes,
        "entities": summary.entities,
        "same_poses": same_poses(folder / "no-viz", folder / "rrd"),
    }


def _method_table(result: dict) -> list[str]:
    """Markdown table of the time spent in each logger method, slowest first."""
    by_time = sorted(result["logger_by_method"].items(), key=lambda kv: -kv[1])
    calls = result["calls_by_method"]
    return table(
        "method | calls | total [s] | per call [ms]",
        (
            [method, calls[method], f"{seconds:.3f}", f"{1e3 * seconds / calls[method]:.2f}"]
            for method, seconds in by_time
        ),
        "lrrr",
    )


def _case_row(r: dict) -> list:
    diff, mb = r["wall_logged_s"] - r["wall_plain_s"], r["rrd_bytes"] / 1e6
    return [
        r["name"],
        r["frames"],
        f"{r['wall_plain_s']:.1f}",
        f"{r['wall_logged_s']:.1f}",
        f"{diff:+.1f} s ({100 * diff / r['wall_plain_s']:+.1f} %)",
        f"{r['logger_s']:.2f}",
        f"{100 * r['logger_s'] / r['wall_logged_s']:.1f} %",
        f"{r['map_logging_plain_s']:.1f} / {r['map_logging_logged_s']:.1f}",
        f"{mb:.1f}",
        f"{100 * mb / r['frames']:.1f}",
        "yes" if r["same_poses"] else "NO",
    ]


def markdown(
    results: list[dict[str, Any]],
    alone: dict[str, Any],
    rates: list[str],
    command: str,
    details: bool,
) -> str:
    """The report: ``rates`` (from :func:`rates_table`), the overhead of each case and of the
    logger alone; with ``details``, each case's time per logger method and largest entities."""
    header = (
        "case | frames | wall no-viz [s] | wall rrd [s] | wall diff | time in logger [s] "
        "| logger / wall rrd | map_logging stage no-viz / rrd [s] | recording [MB] "
        "| MB / 100 frames | identical poses"
    )
    lines = [
        *section_header("rerun", command),
        "",
        "### The pipeline's rate with the default recording",
        "",
        *rates,
        "",
        "### Recording size and logging overhead",
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
        *table(header, map(_case_row, results), "lrrrrrrrrrl"),
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
    for r in results if details else []:
        top = sorted(r["entities"].items(), key=lambda kv: -kv[1].arrow_bytes)[:8]
        lines += [
            "",
            f"### {r['name']}: time inside the logger per method",
            "",
            f"Command: `{r['command']}`",
            "",
            *_method_table(r),
            "",
            f"Largest entities of the recording (uncompressed Arrow bytes; the file is "
            f"{r['rrd_bytes'] / 1e6:.1f} MB):",
            "",
            *table(
                "entity | rows | MB",
                (
                    [entity, stats.rows + stats.static_rows, f"{stats.arrow_bytes / 1e6:.2f}"]
                    for entity, stats in top
                ),
                "lrr",
            ),
        ]
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


def measure_rates(
    trees: dict[str, Path], repeats: int, cases: dict[str, list[str]]
) -> dict[tuple[str, str, str], list]:
    """``{(tree, case, mode): [frames/s per repeat]}``, the repeats interleaved."""
    rates: dict[tuple[str, str, str], list[float]] = defaultdict(list)
    for repeat in range(repeats):
        for case, argv in cases.items():
            for tree, root in trees.items():
                for mode, flags in RATE_MODES.items():
                    run = [*argv, *flags, *RATE_OUTPUTS]
                    rate = pipeline_rate(root, run, WORK_DIR / "rates")
                    rates[(tree, case, mode)].append(rate)
                    say(f"{tree} | {case} | {mode} | run {repeat + 1}: {rate:.2f} frames/s")
    return rates


def rates_table(
    rates: dict, trees: dict[str, Path], repeats: int, cases: dict[str, list[str]]
) -> list[str]:
    """The rates measured by :func:`measure_rates` as Markdown lines."""

    def cell(values: list[float]) -> str:
        return f"{statistics.median(values):.1f} ({min(values):.1f}-{max(values):.1f})"

    rows = []
    for tree in trees:
        for case in cases:
            logged, plain = rates[(tree, case, "recording")], rates[(tree, case, "--no-viz")]
            ratio = statistics.median(logged) / statistics.median(plain)
            rows.append([tree, case, cell(logged), cell(plain), f"{ratio:.2f}"])
    header = "code | case | recording [frames/s] | --no-viz [frames/s] | recording / --no-viz"
    return [
        "Pipeline rate (frames/s from the first frame read to the end of the final optimisation,"
        f" `timing.frames_per_s`) of `python -m slam.run`: median of {repeats} runs (min-max), "
        "interleaved, each in its own process, with the default recording (`recording.rrd`) and "
        "with `--no-viz`.",
        "",
        *table(header, rows, "llrrr"),
    ]


def say(message: str) -> None:
    print(f"bench_rerun: {message}", file=sys.stderr, flush=True)


def build_parser():
    parser = bench_parser(__doc__, "first 30 demo frames only")
    parser.add_argument("--frames", help="frame range of the demo case (overrides the mode)")
    parser.add_argument("--skip-lidar", action="store_true", help="no 1,500-frame LiDAR case")
    parser.add_argument("--rates", action="store_true", help="recording vs --no-viz rates instead")
    parser.add_argument("--before", type=Path, help="--rates: also measure this checkout")
    parser.add_argument("--repeats", type=int, default=3, help="runs of each rate case")
    parser.add_argument(
        "--kitti-root", type=Path, help="--rates: also every scan of sequence 00 in this root"
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    command = command_line("bench_rerun", argv)
    here = {"this checkout": Path(__file__).resolve().parents[1]}
    if args.rates:
        trees = {"before": args.before.resolve(), **here} if args.before else here
        cases = dict(RATE_CASES)
        if args.kitti_root is not None:
            root = args.kitti_root.resolve()
            cases[f"{root.name}, sequence 00, every scan"] = ["kitti", "00", "--root", str(root)]
        rates = measure_rates(trees, args.repeats, cases)
        lines = [
            *section_header("rerun rates", command),
            "",
            *rates_table(rates, trees, args.repeats, cases),
        ]
        write_text_atomic(RATES, "\n".join(lines) + "\n")
        say(f"wrote {RATES}")
        return 0
    rates = rates_table(
        measure_rates(here, args.repeats, RATE_CASES), here, args.repeats, RATE_CASES
    )
    frames = args.frames or ("0:30" if args.quick else None)
    demo = ["demo", *(["--frames", frames] if frames else [])]
    cases = {"demo" + (f" [{frames}]" if frames else ""): demo}
    if not args.quick and not args.skip_lidar:
        kitti = {
            "trajectory": "kitti",
            "kitti_poses": SHARED_KITTI / "poses" / "00.txt",
            "kitti_calib": SHARED_KITTI / "sequences" / "00" / "calib.txt",
            "num_frames": 1500,
        }
        sets = [arg for key, val in kitti.items() for arg in ("--set", f"generated.{key}={val}")]
        if SHARED_KITTI.is_dir():
            cases["generated LiDAR, KITTI 00 trajectory"] = ["generated-lidar", *sets]
        else:
            print(f"skipping the KITTI-trajectory case: {SHARED_KITTI} is absent", file=sys.stderr)
    say("logger alone on the demo frames")
    alone = logger_alone(["demo"])
    results = []
    for name, case_argv in cases.items():
        say(name)
        results.append(measure(name, case_argv))
    write_text_atomic(RESULTS, markdown(results, alone, rates, command, details=not args.quick))
    say(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
