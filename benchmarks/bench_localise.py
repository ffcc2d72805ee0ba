"""Localisation in a stored map: a sequence split in two, the second part localised in the map of
the first (``slam.run --map A --localise``) and continuing it (``slam.run --map A``).

    python -m benchmarks.bench_localise [--quick | --full] [--scenario street room kitchen]
        [--work DIR]

Scenarios (:func:`split`): ``street``, the generated street along KITTI 00 (``--quick``: every
3rd pose of 360-3870, a map of 200 scans, then 151 scans driving the same road again; ``--full``:
the whole window in halves, hours on two cores); ``room``, the generated RGB-D room lap in
halves; ``kitchen``, the real 7-Scenes redkitchen seq-01 in halves (needs ``../shared/data``).
Per scenario: the map run; the second part with ``--localise``, with and without the continuous
map constraints, its error in the map's frame, anchored frames, frames/s and peak RSS; the
odometry alone on the same frames; and ``--map A`` (continuing) with and without the continuous
constraints, the merged run's combined ATE. Writes ``benchmarks/results/localise.md`` and
``.json``.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.harness.child import in_child_measured, run_module
from benchmarks.harness.cli import command_line
from benchmarks.harness.kitti import FULL, KITTI_CALIB, KITTI_POSES, have_kitti
from benchmarks.harness.machine import section_header
from benchmarks.harness.paths import DATA
from benchmarks.harness.results import cm, run_scenarios, scenario_arguments, table, write_results

NO_VIZ = ["--no-viz", "--no-progress", "--set", "output.mesh_samples=0"]
STREET = ["kitti", "00", "--set", "source.kitti.correct_vertical_angle=false"]
ROOM = ["demo", "--set", "generated.num_frames=120"]
KITCHEN_ROOT = DATA / "7scenes_redkitchen"
KITCHEN = ["7scenes", "seq-01", "--root", str(KITCHEN_ROOT)]


@dataclass(frozen=True)
class Split:
    """A scenario: its ``slam.run`` arguments, the map's and the localised run's frames."""

    run_args: list[str]
    map_frames: str
    localised_frames: str
    note: str


def _street_window(full: bool) -> dict[str, Any]:
    """The generated KITTI 00 window (the generator's settings) of the street scenario."""
    if full:
        keys = ("step", "num_frames", "azimuth_steps")
        return {"start": 0, **{k: getattr(FULL, k) for k in keys}}
    return {"start": 360, "step": 3, "num_frames": 1171, "azimuth_steps": 1024}


def street_root(full: bool) -> Path:
    """The KITTI-layout root of the street scenario's window (generated on first use)."""
    from frontends.sources import make_source

    source = make_source(
        "generated", kind="lidar", trajectory="kitti", kitti_poses=KITTI_POSES,
        kitti_calib=KITTI_CALIB, **_street_window(full),
    )  # fmt: skip
    return Path(source.sequence_dir).parents[1]


def split(name: str, full: bool) -> Split:
    if name == "room":
        return Split(ROOM, "0:60", "60:120", "generated RGB-D room lap, 120 frames: 0-59 / 60-119")
    if name == "kitchen":
        if not (KITCHEN_ROOT / "seq-01").is_dir():
            raise FileNotFoundError(f"no 7-Scenes redkitchen seq-01 under {KITCHEN_ROOT}")
        note = "real 7-Scenes redkitchen seq-01, KinectFusion poses: frames 0-199 / 200-399"
        return Split(KITCHEN, "0:200", "200:400", note)
    if not have_kitti():
        raise FileNotFoundError("no KITTI 00 poses/calibration under ../shared/data/kitti")
    root = ["--root", str(street_root(full))]
    if full:
        half = FULL.num_frames // 2
        note = f"KITTI 00 poses 0-{half - 1} / {half}-{FULL.num_frames - 1}, 2048 firings"
        return Split([*STREET, *root], f"0:{half}", f"{half}:{FULL.num_frames}", note)
    note = "KITTI 00 every 3rd pose, 1024 firings: map poses 360-957, localised poses 3420-3870"
    return Split([*STREET, *root], "0:200", "1020:1171", note)


def error_in_map_frame(map_run: Path, run: Path, first_frame: int) -> dict[str, float]:
    """Position error of ``run``'s poses (frames from ``first_frame`` on) against its truth
    carried into the map's frame by the rigid alignment of the map's truth onto its poses."""
    from slam.algorithm.loops.place import _rigid_fit
    from slam.run_folder.trajectory_io import read_kitti

    T = _rigid_fit(
        *(read_kitti(map_run / f"poses_{kind}.kitti.txt")[:, :3, 3] for kind in ("gt", "slam")),
        False,
    )
    poses = read_kitti(run / "poses_slam.kitti.txt")[first_frame:, :3, 3]
    truth = read_kitti(run / "poses_gt.kitti.txt")[first_frame:, :3, 3]
    error = np.linalg.norm(truth @ T[:3, :3].T + T[:3, 3] - poses, axis=1)
    return {"mean_m": float(error.mean()), "worst_m": float(error.max()), "frames": len(error)}


def odometry_alone(config_path: str) -> dict[str, float]:
    """The run's odometry alone on the run's frames (its resolved ``config.yaml``), counted as
    the run counts its ``pipeline_s`` and ``pipeline_cpu_s``: built before the clock starts, under
    the run's thread budget, frames read included, the odometry closed within. frames/s and CPU
    seconds (this process's and the odometry's child process's)."""
    from slam.app.runner import run_cpu_s
    from slam.assembly.builders import build_odometry, build_source
    from slam.assembly.config import load_run_config
    from slam.assembly.threads import apply_thread_budget

    cfg = load_run_config(Path(config_path))
    apply_thread_budget(cfg)
    source = build_source(cfg)
    odometry = build_odometry(cfg, source.sensor)
    cpu_start = run_cpu_s(odometry)
    count, start = 0, time.perf_counter()
    for frame in source.read_ahead():
        odometry.register(frame)
        count += 1
    odometry.close()
    wall = time.perf_counter() - start
    cpu = run_cpu_s(None) - cpu_start  # the odometry's child was waited for
    return {"frames": count, "wall_s": wall, "frames_per_s": count / wall, "cpu_s": cpu}


def _second_part(
    spec: Split, work: Path, name: str, *, continuous: bool, localise: bool, sets: tuple = ()
):
    """The second part on the map in ``work``: localised in it, or (``localise`` False)
    continuing it; with or without the continuous map constraints; ``sets``: more
    ``--set KEY=VALUE`` overrides."""
    out = work / name
    sets = [*(["--set", "relocalise.continuous=false"] if not continuous else []), *sets]
    args = [*spec.run_args, "--frames", spec.localised_frames, *NO_VIZ, *sets]
    args += ["--map", str(work / "map"), *(["--localise"] if localise else []), "--out", str(out)]
    wall, rss = run_module("slam.run", args, work / f"{name}.log")
    metrics = json.loads((out / "metrics.json").read_text())
    if not localise:
        return {
            "wall_s": wall,
            "peak_rss_mb": rss,
            "combined_ate_m": metrics.get("combined_ate_rmse_m"),
        }
    placed = metrics["relocalisation"]
    first = metrics["localisation"]["frames_before_placement"]
    return {
        "wall_s": wall,
        "peak_rss_mb": rss,
        "frames_per_s": metrics["timing"]["frames_per_s"],
        "pipeline_cpu_s": metrics["timing"]["pipeline_cpu_s"],
        "map_decode_s": placed["map_decode_seconds"],
        "placed_by_frames": placed.get("submap_frames"),
        "localisation": metrics["localisation"],
        "error_after_placement": error_in_map_frame(work / "map", out, first),
        "config": str(out / "config.yaml"),
    }


def scenario(name: str, full: bool, work: Path) -> dict[str, Any]:
    spec = split(name, full)
    args = [*spec.run_args, "--frames", spec.map_frames, *NO_VIZ, "--out", str(work / "map")]
    wall, rss = run_module("slam.run", args, work / "map.log")
    own = json.loads((work / "map" / "metrics.json").read_text())
    result: dict[str, Any] = {
        "note": spec.note,
        "map": {
            "wall_s": wall,
            "peak_rss_mb": rss,
            "ate_m": own["trajectory"]["slam"]["ate_rmse_m"],
        },
        "localise": _second_part(spec, work, "localise", continuous=True, localise=True),
        "localise_placement_only": _second_part(
            spec, work, "localise-placement-only", continuous=False, localise=True
        ),
    }
    from slam.assembly.config import load_run_config

    config = load_run_config(Path(result["localise"]["config"]))
    if config.submaps.localise_scan_spacing_m is not None:
        result["localise_every_scan"] = _second_part(
            spec, work, "localise-every-scan", continuous=True, localise=True,
            sets=("--set", "submaps.localise_scan_spacing_m=null"),
        )  # fmt: skip
    alone, usage = in_child_measured(odometry_alone, result["localise"]["config"])
    result["odometry_alone"] = {**alone, "peak_rss_mb": usage.peak_rss_mb}
    result["continue"] = _second_part(spec, work, "continue", continuous=True, localise=False)
    result["continue_placement_only"] = _second_part(
        spec, work, "continue-placement-only", continuous=False, localise=False
    )
    return result


def _cpu_ms(cpu_s: float | None, frames: int) -> str:
    return "-" if cpu_s is None else f"{1e3 * cpu_s / max(frames, 1):.0f}"


def _rows(r: dict[str, Any]) -> list[list]:
    rows = []
    placement_only = "placement only (`relocalise.continuous=false`)"
    every_scan = "continuous, every scan (`submaps.localise_scan_spacing_m=null`)"
    for key, label in (
        ("localise", "continuous (default)"),
        ("localise_every_scan", every_scan),
        ("localise_placement_only", placement_only),
    ):
        if key not in r:
            continue
        run = r[key]
        e, loc = run["error_after_placement"], run["localisation"]
        gaps = ", ".join(f"{a}-{b}" for a, b in loc["coverage_gaps"][:4]) or "none"
        rows.append(
            [
                f"`--localise`, {label}",
                f"{cm(e['mean_m'])} / {cm(e['worst_m'])} ({e['frames']} frames)",
                f"{100 * loc['fraction_anchored']:.0f} % ({loc['frames_before_placement']} "
                f"before placement; gaps {gaps})",
                f"{run['frames_per_s']:.1f}",
                _cpu_ms(run["pipeline_cpu_s"], loc["frames"]),
                f"{run['map_decode_s']:.1f}",
                f"{run['peak_rss_mb']:.0f}",
            ]
        )
    return rows


def report(results: dict[str, Any], command: str) -> str:
    lines = [
        *section_header("Localisation in a stored map", command),
        "- The map: the first part run on its own. The second part runs with `--map map "
        "--localise` (poses only) and with `--map map` (continuing the map, merged at the end), "
        "each with the continuous map constraints (default) and with the first placement only; "
        "where the config spaces a placed run's scans (`submaps.localise_scan_spacing_m`), also "
        "with every scan. "
        "Error: against the truth carried into the map's frame by aligning the map's own truth "
        "onto its poses, from the placing submap on (the map's ATE is aligned on itself). "
        "frames/s: the run's pipeline rate; the stored surfaces are decoded before the first "
        "frame (`decode`). Odometry alone: the same config's odometry on the same frames in its "
        "own process, timed as the run is. CPU: the process's and the odometry child's CPU time "
        "over those frames (`timing.pipeline_cpu_s`), decode excluded; on two shared cores the "
        "localisation cannot outrun the odometry once it needs more CPU a frame than the "
        "odometry leaves idle.",
        "",
    ]
    for name, r in results.items():
        if "skipped" in r:
            lines += [f"### {name}", "", f"Skipped: {r['skipped']}.", ""]
            continue
        odo = r["odometry_alone"]
        lines += [
            f"### {name} ({r['note']})", "",
            f"Map: ATE {cm(r['map']['ate_m'])} cm (on itself), peak RSS "
            f"{r['map']['peak_rss_mb']:.0f} MB. Odometry alone on the localised frames: "
            f"{odo['frames_per_s']:.1f} frames/s ({odo['frames']} frames), "
            f"{_cpu_ms(odo.get('cpu_s'), odo['frames'])} ms of CPU a frame.", "",
            *table("run | error in the map's frame, mean / worst frame [cm] | map-anchored "
                   "frames | frames/s | CPU [ms/frame] | decode [s] | peak RSS [MB]", _rows(r),
                   "lllrrrr"), "",
            *table("`--map map` (continue mapping) | merged combined ATE [cm] | peak RSS [MB]",
                   ([label, cm(r[key]["combined_ate_m"]), f"{r[key]['peak_rss_mb']:.0f}"]
                    for label, key in (("placement only (before)", "continue_placement_only"),
                                       ("continuous (after)", "continue"))), "lrr"), "",
        ]  # fmt: skip
    return "\n".join(lines) + "\n"


SCENARIOS = ("street", "room", "kitchen")
"""Every mode runs all three by default (quick: about 2 + 1 + 4 minutes on two cores)."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="the short street split")
    mode.add_argument("--full", action="store_true", help="the whole street in halves (hours)")
    scenario_arguments(parser, SCENARIOS, "all three")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    names = args.scenario or SCENARIOS
    results = run_scenarios(
        names, lambda name, work: scenario(name, args.full, work), "localise", args.work
    )
    write_results("localise", results, report(results, command_line("bench_localise", argv)))


if __name__ == "__main__":
    main()
