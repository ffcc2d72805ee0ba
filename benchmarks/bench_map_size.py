"""Map size and memory against the raw points the map replaces, before and after a change.

    python -m benchmarks.bench_map_size [--before REV] [--scenarios demo 7scenes]
                                        [--out benchmarks/results/map_size.md]

Every scenario runs ``python -m slam.run ... --no-viz`` in its own process, with this checkout
and, with ``--before``, with REV checked out beside it. Reported per run: ``map.npz`` size, voxels
stored in submaps and their bytes, global voxels and the overlap factor; peak RSS (sampled as the
trajectory file grows: peak RSS by sequence length), frames/s, ATE and mesh accuracy; and the
raw-data baseline: the same submaps' points replayed through the keyframer and downsampled to
V/4, as float32 (what re-fusing raw points after loop closure would keep). Scenarios: the
generated room, 7-Scenes redkitchen (skipped without ../shared/data), and the first 1,000 or all
4,541 scans of the generated street along KITTI 00.
"""

from __future__ import annotations

import json
import logging
import os
import shlex
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.harness.checkout import revisions
from benchmarks.harness.child import run_command
from benchmarks.harness.cli import bench_parser, command_line, start_logging
from benchmarks.harness.kitti import kitti_root, kitti_source
from benchmarks.harness.machine import proc_memory_kib, section_header
from benchmarks.harness.paths import DATA, REPO, RESULTS_DIR
from benchmarks.harness.repeat import REPEATS, repeat_runs, repeats_line
from benchmarks.harness.results import cm
from common.atomic_io import write_text_atomic

RSS_CHECKPOINTS = (500, 1000, 2000, 3000, 4000)
SCENARIOS: dict[str, list[str]] = {
    "demo": ["demo"],
    "demo-100": ["demo", "--frames", "0:100"],
    "7scenes": [
        "7scenes",
        "seq-01",
        "--root",
        str(DATA / "7scenes_redkitchen"),
        "--frames",
        "0:400",
    ],
    "kitti-1000": ["kitti", "00", "--frames", "0:1000"],  # --root added by kitti_root()
    "kitti-full": ["kitti", "00"],
}


def _vm_hwm_mb(pid: int) -> float | None:
    peak = proc_memory_kib(pid).get("VmHWM")
    return None if peak is None else peak / 1024


def _frames_written(run_dir: Path) -> int:
    try:
        with open(run_dir / "poses_odometry.kitti.txt", "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return 0


log = logging.getLogger("benchmarks.bench_map_size")


def run_slam(checkout: Path, args: list[str], out: Path) -> dict[str, Any]:
    """``slam.run`` from ``checkout`` as a measured child process: its metrics, wall time and
    peak RSS, and the peak RSS reached by each of RSS_CHECKPOINTS frames."""
    env = dict(os.environ, PYTHONPATH=str(checkout), PYTHONUNBUFFERED="1")
    command = [sys.executable, "-m", "slam.run", *args, "--no-viz", "--out", str(out)]
    log.info("%s: %s", checkout, shlex.join(command))
    rss_at: dict[int, float] = {}

    def sample(pid: int) -> None:
        frames, peak = _frames_written(out), _vm_hwm_mb(pid)
        for checkpoint in RSS_CHECKPOINTS:
            if frames >= checkpoint and checkpoint not in rss_at and peak is not None:
                rss_at[checkpoint] = peak

    log_file = out.parent / f"{out.name}.log"
    run = run_command(command, cwd=checkout, env=env, log_file=log_file, on_poll=sample)
    if run.returncode != 0:
        raise RuntimeError(f"slam.run failed in {checkout}; see {log_file}")
    metrics = json.loads((out / "metrics.json").read_text())
    peak = run.usage.peak_rss_mb
    # the run's own peak before it scores its mesh against ground truth (newer runs report it)
    slam_peak = metrics.get("memory", {}).get("peak_rss_before_scoring_mb")
    rss_at[metrics["num_frames"]] = slam_peak if slam_peak is not None else peak
    return {
        "metrics": metrics,
        "wall_s": run.usage.wall_s,
        "peak_rss_mb": peak,
        "slam_peak_rss_mb": slam_peak,
        "rss_at_frames": rss_at,
    }


def map_file_stats(path: Path) -> dict[str, Any]:
    """Size and content of a ``map.npz`` (the submaps' arrays and a header; one weight a voxel)."""
    with np.load(path, allow_pickle=False) as npz:
        submap_arrays = [n for n in npz.files if not n.startswith("submap_") and n != "header"]
        voxels = int(npz["weights"].shape[0])
        submap_bytes = sum(npz[n].nbytes for n in submap_arrays)
    return {
        "file_mb": path.stat().st_size / 1e6,
        "submap_voxels": voxels,
        "bytes_per_submap_voxel": submap_bytes / max(voxels, 1),
        "file_bytes_per_submap_voxel": path.stat().st_size / max(voxels, 1),
    }


def raw_baseline(run_dir: Path) -> dict[str, Any]:
    """Points of the run's submaps at V/4, replayed through the keyframer with its odometry."""
    from kiss_icp.voxelization import voxel_down_sample

    from slam.algorithm.submaps import Keyframer
    from slam.assembly.builders import build_source
    from slam.assembly.config import load_run_config
    from slam.run_folder.trajectory_io import read_kitti

    cfg = load_run_config(run_dir / "config.yaml")
    poses = read_kitti(run_dir / "poses_odometry.kitti.txt")
    source = build_source(cfg)
    if source.sensor != "rgbd":
        raise ValueError("the keyframer replay reproduces RGB-D submaps only (LiDAR deskews)")
    cfg.submaps.keep_keyframe_images = False
    keyframer = Keyframer(cfg.submaps)
    quarter = cfg.mapping.voxel_size_m / 4
    counts: list[int] = []
    for frame, T_W_S in zip(source, poses, strict=True):
        closed, _, _ = keyframer.add(frame, T_W_S)
        if closed is not None:
            counts.append(len(voxel_down_sample(closed.points_A, quarter)))
    last = keyframer.finish()
    if last is not None:
        counts.append(len(voxel_down_sample(last.points_A, quarter)))
    points = int(sum(counts))
    return {
        "submaps": len(counts),
        "points": points,
        "points_mb": 12 * points / 1e6,
        "points_normals_mb": 24 * points / 1e6,
    }


def measure(checkout: Path, name: str, work: Path, with_raw: bool) -> dict[str, Any]:
    """``REPEATS`` runs of a scenario (one for the long KITTI ones): the first run's sizes and
    memory, the runs' wall time and frames/s."""
    args = SCENARIOS[name]
    if name.startswith("kitti"):
        args = [*args, "--root", str(kitti_root(kitti_source(quick=False)))]
    outs = iter(work / f"{name}-{checkout.name}-{k}" for k in range(REPEATS))

    def run() -> dict[str, Any]:
        result = run_slam(checkout, args, next(outs))
        return {**result, "fps": _metric(result["metrics"], "timing", "frames_per_s")}

    result = repeat_runs(run, ("wall_s", "fps"), 1 if name.startswith("kitti") else REPEATS)
    out = work / f"{name}-{checkout.name}-0"
    result["map"] = map_file_stats(out / "map.npz")
    if with_raw:
        result["raw"] = raw_baseline(out)
    return result


def _metric(metrics: dict[str, Any], *keys: str) -> float | None:
    value: Any = metrics
    for key in keys:
        if not isinstance(value, dict) or key not in value:
            return None
        value = value[key]
    return value


def _repeated(run: dict[str, Any], key: str, digits: int) -> str:
    """A repeated timing; a single run's is not shown (the KITTI runs: see bench_throughput)."""
    if run.get("repeats", 1) < REPEATS:
        return "- (one run)"
    return f"{run[key]:.{digits}f}"


def _ate(r: dict[str, Any]) -> str:
    ate = [_metric(r["metrics"], "trajectory", kind, "ate_rmse_m") for kind in ("odometry", "slam")]
    return " -> ".join(cm(v, 2) for v in ate)


ROWS = (
    ("`map.npz` [MB]", lambda r: f"{r['map']['file_mb']:.1f}"),
    ("submaps", lambda r: str(r["metrics"]["num_submaps"])),
    ("voxels stored in submaps", lambda r: f"{r['map']['submap_voxels']:,}"),
    (
        "bytes per stored submap voxel (arrays / on disk)",
        lambda r: (
            f"{r['map']['bytes_per_submap_voxel']:.0f} / "
            f"{r['map']['file_bytes_per_submap_voxel']:.0f}"
        ),
    ),
    ("global map voxels", lambda r: f"{r['metrics']['map']['voxels']:,}"),
    (
        "overlap (stored / global voxels)",
        lambda r: f"{r['map']['submap_voxels'] / max(r['metrics']['map']['voxels'], 1):.2f}",
    ),
    ("peak RSS of the run, scoring included [MB]", lambda r: f"{r['peak_rss_mb']:.0f}"),
    (
        "peak RSS before scoring against ground truth [MB]",
        lambda r: "-" if r.get("slam_peak_rss_mb") is None else f"{r['slam_peak_rss_mb']:.0f}",
    ),
    (
        "peak RSS after N frames (last: before scoring, where reported) [MB]",
        lambda r: ", ".join(f"{n}: {mb:.0f}" for n, mb in sorted(r["rss_at_frames"].items())),
    ),
    ("wall time of the run [s]", lambda r: _repeated(r, "wall_s", 0)),
    ("frames/s (as the run reports it)", lambda r: _repeated(r, "fps", 1)),
    ("ATE odometry -> SLAM [cm]", _ate),
    ("mesh accuracy [cm]", lambda r: cm(_metric(r["metrics"], "mesh", "accuracy_m"), 2)),
)
"""The table's rows: a title and the cell of one run."""


def table(name: str, runs: dict[str, dict[str, Any]]) -> list[str]:
    """One Markdown table, a column per run (before / after)."""
    labels = list(runs)
    lines = [f"### {name}", "", "| | " + " | ".join(labels) + " |", "|---|" + "---:|" * len(labels)]
    lines += [
        f"| {title} | " + " | ".join(cell(runs[label]) for label in labels) + " |"
        for title, cell in ROWS
    ]
    raw = runs[labels[-1]].get("raw")
    if raw is not None:
        ours = runs[labels[-1]]["map"]["file_mb"]
        lines += [
            "",
            f"Raw-data baseline (the same {raw['submaps']} submaps' points at V/4, float32): "
            f"{raw['points']:,} points = **{raw['points_mb']:.1f} MB** "
            f"({raw['points_normals_mb']:.1f} MB with normals). `map.npz` "
            f"({labels[-1]}) is {ours / raw['points_mb']:.2f}x the points alone.",
        ]
    return [*lines, ""]


def build_parser():
    parser = bench_parser(
        __doc__, "the first 100 demo frames only", before=True, out=RESULTS_DIR / "map_size.md"
    )
    parser.add_argument(
        "--scenarios",
        nargs="+",
        choices=list(SCENARIOS),
        help="default: demo, 7scenes and kitti-full (--quick: demo)",
    )
    parser.add_argument(
        "--after-only",
        nargs="*",
        default=[],
        choices=list(SCENARIOS),
        help="scenarios measured with this checkout only",
    )
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    start_logging()
    if args.scenarios is None:
        args.scenarios = ["demo-100"] if args.quick else ["demo", "7scenes", "kitti-full"]
    if "7scenes" in args.scenarios and not (DATA / "7scenes_redkitchen").is_dir():
        log.warning("skipping 7scenes: %s is absent", DATA / "7scenes_redkitchen")
        args.scenarios.remove("7scenes")
    command = command_line("bench_map_size", argv)
    lines = [
        *section_header("Map size and memory (lean map)", command),
        "- Revisions: after = this checkout"
        + (f"; before = `{args.before}`, checked out beside it" if args.before else ""),
        "- Each run is `python -m slam.run ... --no-viz` in its own process; peak RSS is that "
        "process's maximum resident set size.",
        repeats_line(
            "Sizes, memory and accuracy are the first run's. The KITTI scenarios run once (their "
            "wall time is bench_throughput's); --quick: the first 100 demo frames."
        ),
        "",
    ]
    with (
        tempfile.TemporaryDirectory(prefix="bench_map_size-") as tmp,
        revisions(args.before, "before ({rev})") as codes,
    ):
        work = Path(tmp)
        for name in args.scenarios:
            runs = {}
            for label, code in codes.items():
                if label != "after" and name in args.after_only:
                    continue
                rgbd = not name.startswith("kitti")
                runs[label] = measure(code or REPO, name, work, with_raw=rgbd and label == "after")
                log.info("%s %s: %s", name, label, json.dumps(runs[label]["map"]))
            lines += table(name, runs)
    text = "\n".join(lines) + "\n"
    write_text_atomic(args.out, text)
    log.info("wrote %s", args.out)


if __name__ == "__main__":
    main()
