"""Many recordings on Ray: ``python -m slam.fleet`` against the same runs one after the other,
and one global merge against pairwise merges in a tree.

    python -m benchmarks.bench_fleet [--quick]

Sessions are overlapping windows of the generated RGB-D room. 1. Four sessions: ``slam.run`` on
each in turn then ``slam.merge``, against ``slam.fleet`` on a local Ray with 2 CPUs: wall time
and peak memory (the largest serial process against the fleet's whole process tree, sampled
twice a second). 2. The fleet again with eight sessions, the four finished reused. 3. Merges of
2, 4 and 8 sessions: one global ``slam.merge`` against the tree ``slam.fleet --merge tree`` runs
(its critical path is what a cluster running each level at once would wait). 4. On paper: 100
drives on a 16-node cluster, from these per-task figures. Writes ``benchmarks/results/fleet.md``
and ``.json``.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from benchmarks.harness.child import run_command
from benchmarks.harness.cli import bench_parser
from benchmarks.harness.machine import proc_memory_kib, section_header
from benchmarks.harness.paths import REPO
from benchmarks.harness.results import write_results
from slam.app.fleet_plan import TASK_MEMORY_MB, merge_levels

# quick: the 120-frame lap, coarse depth/map/mesh, 24-frame windows; full: `slam.run demo` as
# it is (240 frames), 60-frame windows
QUICK = {
    "frames": 120, "window": 24, "stride": 14,
    "set": {"generated.num_frames": 120, "source.depth.stride": 4, "mapping.voxel_size_m": 0.2,
            "mapping.mesh_subdivisions": 2, "output.mesh_samples": 0},
}  # fmt: skip
FULL = {"frames": 240, "window": 60, "stride": 28, "set": {"output.mesh_samples": 0}}
CLUSTER = {"drives": 100, "nodes": 16, "cores": 16, "memory_gb": 64, "drive_frames": 4541}


def _windows(mode: dict, count: int) -> list[str]:
    starts = [k * mode["stride"] for k in range(count)]
    return [f"{a}:{min(a + mode['window'], mode['frames'])}" for a in starts]


def _set_args(mode: dict) -> list[str]:
    return [a for key, value in mode["set"].items() for a in ("--set", f"{key}={value}")]


def _tree_rss_mb(root_pid: int) -> float:
    """Resident memory of ``root_pid`` and all its descendants (from /proc)."""
    children: dict[int, list[int]] = {}
    rss: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(entry.name))
        rss[int(entry.name)] = proc_memory_kib(entry.name).get("VmRSS", 0)
    total, stack = 0, [root_pid]
    while stack:
        pid = stack.pop()
        total += rss.get(pid, 0)
        stack.extend(children.get(pid, []))
    return total / 1024


def _measure(command: list[str], log: Path) -> dict[str, Any]:
    """Run ``command``; wall time, exit status, own peak RSS and the peak of its process tree."""
    peak = [0.0]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    result = run_command(
        [sys.executable, *command], cwd=REPO, env=env, log_file=log,
        on_poll=lambda pid: peak.__setitem__(0, max(peak[0], _tree_rss_mb(pid))),
    )  # fmt: skip
    if result.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed; see {log}")
    return {"wall_s": result.usage.wall_s, "peak_rss_mb": result.usage.peak_rss_mb,
            "tree_peak_mb": max(peak[0], result.usage.peak_rss_mb)}  # fmt: skip


def _run_metrics(folder: Path) -> dict[str, Any]:
    metrics = json.loads((folder / "metrics.json").read_text())
    return {"frames": metrics["num_frames"], "wall_s": metrics["timing"]["wall_s"],
            "peak_rss_mb": metrics["memory"]["peak_rss_mb"]}  # fmt: skip


def serial(mode: dict, work: Path, windows: list[str]) -> dict[str, Any]:
    runs = []
    for k, frames in enumerate(windows):
        command = ["-m", "slam.run", "demo", "--frames", frames, "--no-viz", "--no-progress",
                   "--out", str(work / f"s{k}"), *_set_args(mode)]  # fmt: skip
        runs.append(_measure(command, work / f"s{k}.log"))
    merged = _measure(
        [
            "-m",
            "slam.merge",
            *(str(work / f"s{k}") for k in range(len(windows))),
            "--out",
            str(work / "s-merged"),
            "--no-viz",
        ],
        work / "s-merge.log",
    )
    return {
        "wall_s": sum(r["wall_s"] for r in runs) + merged["wall_s"],
        "peak_mb": max(r["peak_rss_mb"] for r in [*runs, merged]),
        "runs": runs, "merge": merged,
    }  # fmt: skip


def fleet(mode: dict, work: Path, windows: list[str], out: Path, tag: str) -> dict[str, Any]:
    manifest = work / f"{tag}.yaml"
    entries = [{"name": f"w{k}", "dataset": "demo", "frames": frames, "set": mode["set"]}
               for k, frames in enumerate(windows)]  # fmt: skip
    manifest.write_text(yaml.safe_dump(entries, sort_keys=False))
    command = ["-m", "slam.fleet", str(manifest), "--out", str(out), "--num-cpus", "2",
               "--no-progress"]  # fmt: skip
    measured = _measure(command, work / f"{tag}.log")
    measured["tasks"] = [_run_metrics(out / "runs" / f"w{k}") for k in range(len(windows))]
    measured["reused"] = (work / f"{tag}.log").read_text().count("finished earlier, reused")
    return measured


def _combined_ate(folder: Path) -> float | None:
    return json.loads((folder / "metrics.json").read_text()).get("combined_ate_rmse_m")


def merges(runs: list[Path], work: Path, counts: tuple[int, ...]) -> list[dict[str, Any]]:
    """Global and tree merges of the first ``n`` runs for each ``n``. A merge of the same runs
    in the same order is run once: the tree of 4 is part of the tree of 8, and a merge of 2 is
    both the global merge and the tree's first pair."""
    done: dict[tuple[Path, ...], tuple[Path, dict[str, Any]]] = {}

    def merge(inputs: list[Path], covered: list[Path], out: Path) -> tuple[Path, dict]:
        key = tuple(covered)
        if key not in done:
            log = work / f"merge-{len(done)}.log"
            command = ["-m", "slam.merge", *map(str, inputs), "--out", str(out), "--no-viz"]
            done[key] = (out, _measure(command, log))
        return done[key]

    rows = []
    for n in counts:
        folders = runs[:n]
        out, measured = merge(folders, folders, work / f"global{n}")
        row: dict[str, Any] = {
            "sessions": n,
            "global": {**measured, "ate_m": _combined_ate(out), "submaps": _submaps(out)},
        }
        alias: dict[Path, Path] = {}
        walls, critical, peak = [], 0.0, 0.0
        for level in merge_levels(folders, work / f"tree{n}", tree=True):
            level_max = 0.0
            for step in level:
                inputs = [alias.get(folder, folder) for folder in step.inputs]
                alias[step.out], step_measured = merge(inputs, step.runs, step.out)
                walls.append(step_measured["wall_s"])
                level_max = max(level_max, step_measured["wall_s"])
                peak = max(peak, step_measured["peak_rss_mb"])
            critical += level_max
        final = alias[work / f"tree{n}" / "merged"]
        row["tree"] = {"merges": len(walls), "wall_s": sum(walls), "critical_s": critical,
                       "peak_rss_mb": peak, "ate_m": _combined_ate(final)}  # fmt: skip
        rows.append(row)
    return rows


def _submaps(folder: Path) -> int:
    return int(json.loads((folder / "metrics.json").read_text())["submaps"])


def projection(results: dict[str, Any]) -> dict[str, Any]:
    """100 drives on 16 nodes, from the measured per-task figures (see the report's text)."""
    tasks = results["fleet4"]["tasks"]
    per_frame_s = float(np.median([t["wall_s"] / t["frames"] for t in tasks]))
    c = CLUSTER
    threads = max(1, (c["nodes"] * c["cores"]) // c["drives"])
    per_node = min(c["cores"] // threads, int(c["memory_gb"] * 1024 // TASK_MEMORY_MB["lidar"]))
    waves = -(-c["drives"] // (c["nodes"] * per_node))
    submaps = np.array([r["global"]["submaps"] for r in results["merges"]], dtype=float)
    walls = np.array([r["global"]["wall_s"] for r in results["merges"]])
    mems = np.array([r["global"]["peak_rss_mb"] for r in results["merges"]])
    time_fit = np.polyfit(submaps, walls, 2)
    memory_fit = np.polyfit(submaps, mems, 1)
    sessions = np.array([r["sessions"] for r in results["merges"]], dtype=float)
    submaps_per_frame = float(np.mean(submaps / (sessions * results["window"])))
    like_here = c["drives"] * results["window"] * submaps_per_frame
    drives = c["drives"] * c["drive_frames"] * submaps_per_frame
    return {
        "per_frame_s": per_frame_s, "threads": threads, "tasks_per_node": per_node,
        "waves": waves, "submaps_per_frame": submaps_per_frame,
        "merge_s_per_submap_pair": float(time_fit[0]),
        "merge_s_like_here": float(np.polyval(time_fit, like_here)),
        "merge_mb_like_here": float(np.polyval(memory_fit, like_here)),
        "merge_s_drives": float(np.polyval(time_fit, drives)),
        "merge_mb_drives": float(np.polyval(memory_fit, drives)),
        "submaps_drives": drives,
    }  # fmt: skip


def report(results: dict[str, Any], command: str) -> str:
    s, f4, f8 = results["serial"], results["fleet4"], results["fleet8"]
    serial_runs = ", ".join(f"{r['wall_s']:.1f}" for r in s["runs"])
    fleet_tasks = ", ".join(f"{t['wall_s']:.1f}" for t in f4["tasks"])
    task_peak = max(t["peak_rss_mb"] for t in f4["tasks"])
    lines = [*section_header("Many recordings on Ray (slam.fleet)", command),
             f"- Sessions: windows of {results['window']} frames of the generated room, "
             f"{', '.join(results['windows'])}; {results['mode']} settings", "",
             "| 4 sessions | wall s | peak memory MB |", "|---|---:|---:|",
             f"| serial: slam.run x4 then slam.merge | {s['wall_s']:.1f} | {s['peak_mb']:.0f} "
             "(largest process) |",
             f"| slam.fleet, local Ray, 2 CPUs | {f4['wall_s']:.1f} | {f4['tree_peak_mb']:.0f} "
             "(driver + Ray + tasks) |", "",
             f"Serial runs: {serial_runs} s each, merge "
             f"{s['merge']['wall_s']:.1f} s. Fleet tasks (their own wall, one thread each, two at "
             f"once): {fleet_tasks} s, peak RSS {task_peak:.0f} MB. The same folder with 8 "
             f"sessions: {f8['reused']} runs reused, {f8['wall_s']:.1f} s. The fleet's wall "
             f"holds starting Ray and, per task, a worker process and its imports; the serial "
             f"runs' holds their own imports. With sessions of seconds on 2 cores, that and "
             f"the machine's other jobs take what running two at once gains; the gain is the "
             f"runs' share of the wall, which grows with the sessions' length and the cores. "
             f"The fleet's memory adds Ray's own processes (its GCS, raylet and idle workers) "
             f"to the tasks'.", "",
             "| sessions | global merge s | its peak MB | tree: merges | tree s (one after the "
             "other) | tree critical path s | tree peak MB | combined ATE cm global / tree |",
             "|---:|---:|---:|---:|---:|---:|---:|---|"]  # fmt: skip
    for r in results["merges"]:
        g, t = r["global"], r["tree"]
        ate = "/".join("-" if x["ate_m"] is None else f"{100 * x['ate_m']:.2f}" for x in (g, t))
        lines.append(f"| {r['sessions']} | {g['wall_s']:.1f} | {g['peak_rss_mb']:.0f} | "
                     f"{t['merges']} | {t['wall_s']:.1f} | {t['critical_s']:.1f} | "
                     f"{t['peak_rss_mb']:.0f} | {ate} |")  # fmt: skip
    p, c = results["projection"], CLUSTER
    drive_s = p["per_frame_s"] * c["drive_frames"]
    lines += ["", "### 100 drives on a 16-node cluster, on paper", "",
              f"Assumed: {c['drives']} drives of {c['drive_frames']} frames (the length of KITTI "
              f"00), {c['nodes']} nodes of {c['cores']} cores and {c['memory_gb']} GB. "
              f"`slam.fleet` gives each run {p['threads']} threads ({c['nodes'] * c['cores']} "
              f"CPUs / {c['drives']} runs), so {p['tasks_per_node']} tasks fit a node by CPU "
              f"and by memory (LiDAR: {TASK_MEMORY_MB['lidar']} MB each): the runs go in "
              f"{p['waves']} wave(s). The runs: at the {1e3 * p['per_frame_s']:.0f} ms a frame "
              f"measured per task here (a run's wall over its frames, fixed costs included; "
              f"RGB-D on one thread of a loaded 2-core machine; substitute the sensor's own "
              f"figure) a drive, and so the wave, takes {drive_s / 60:.0f} min.", "",
              f"The merge is one task on one node, and it is what such a fleet waits for. A "
              f"quadratic fit of the global merge's time over its submaps "
              f"({p['submaps_per_frame']:.2f} submaps a frame here; candidate matching "
              f"compares every pair of submaps) gives "
              f"{p['merge_s_like_here']:.0f} s and {p['merge_mb_like_here']:.0f} MB for 100 "
              f"sessions as short as these, but {p['merge_s_drives'] / 3600:.0f} h and "
              f"{p['merge_mb_drives'] / 1024:.0f} GB (linear fit of memory) for "
              f"{p['submaps_drives']:.0f} submaps of 100 full drives at this submap rate: the "
              f"pairwise candidate search has to become an index before 100 full drives are "
              f"merged in one piece. A tree does not avoid it: its last merge alone still "
              f"compares the two halves' submaps, a quarter of all pairs, and every level "
              f"re-meshes the whole map ({_tree_verdict(results['merges'][-1])}).", ""]  # fmt: skip
    return "\n".join(lines) + "\n"


def _tree_verdict(row: dict[str, Any]) -> str:
    g, t = row["global"], row["tree"]
    return (
        f"{row['sessions']} sessions: the tree's critical path {t['critical_s']:.1f} s "
        f"against the global merge's {g['wall_s']:.1f} s, peak {t['peak_rss_mb']:.0f} "
        f"against {g['peak_rss_mb']:.0f} MB"
    )


def build_parser():
    return bench_parser(__doc__, "coarse settings, short windows")


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    mode = QUICK if args.quick else FULL
    windows = _windows(mode, 8)
    work = Path(tempfile.mkdtemp(prefix="bench-fleet-"))
    try:  # the room is generated once, outside every measurement
        _measure(["-m", "slam.run", "demo", "--frames", "0:2", "--no-viz", "--no-progress",
                  "--out", str(work / "warm"), *_set_args(mode)], work / "warm.log")  # fmt: skip
        results: dict[str, Any] = {"mode": "quick" if args.quick else "full",
                                   "window": mode["window"], "windows": windows}  # fmt: skip
        results["serial"] = serial(mode, work, windows[:4])
        out = work / "fleet"
        results["fleet4"] = fleet(mode, work, windows[:4], out, "fleet4")
        results["fleet8"] = fleet(mode, work, windows, out, "fleet8")
        runs = [out / "runs" / f"w{k}" for k in range(8)]
        results["merges"] = merges(runs, work, (2, 4, 8))
        results["projection"] = projection(results)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    command = "python -m benchmarks.bench_fleet" + (" --quick" if args.quick else "")
    write_results("fleet", results, report(results, command))


if __name__ == "__main__":
    main()
