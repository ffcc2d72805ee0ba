"""Trajectory accuracy of the RGB-D pipeline and of every loop edge against ground truth.

    python -m benchmarks.bench_accuracy [--before REV] [--quick] [--out FILE.md]
    python -m benchmarks.bench_accuracy --report-only

Runs, each in its own process (``NullLogger``, map on the CPU, one torch thread):

* real 7-Scenes redkitchen seq-01 frames 0-399 with configs/7scenes.yaml (skipped when
  ../shared/data is absent);
* the generated RGB-D room with configs/demo.yaml.

``--before REV`` runs the same scenarios with revision REV, checked out beside this tree, in the
same invocation, so both end up in one before/after table. For every run the section lists each
verified loop edge's error against the ground-truth relative pose of the two anchors, and
whether the pose graph kept it. ``benchmarks/results/accuracy.json`` holds this invocation only.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import json
import logging
import os
import shlex
import sys
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.harness.checkout import checkout
from benchmarks.harness.child import UnsupportedRevision, in_child
from benchmarks.harness.machine import git_revision, machine_line
from benchmarks.harness.paths import DATA, REPO, RESULTS_DIR
from benchmarks.harness.pipeline import anchor_frames, load_config, run_pipeline, trajectory_summary
from benchmarks.harness.repeat import repeat_runs, repeats_line
from common.atomic_io import write_text_atomic
from slam.assembly.config import merge_overrides

RESULTS = RESULTS_DIR

log = logging.getLogger("benchmarks.bench_accuracy")


def _depth_agreements(pipeline, source, a: int, b: int, T_a_b: np.ndarray, truth: np.ndarray):
    """Fraction of keyframe ``a``'s depth that agrees (3 cm) with keyframe ``b``'s, moved by the
    loop edge and by the ground truth: a check of the ground truth that needs no ground truth."""
    from slam.algorithm.loops.keyframes import depth_agreement
    from slam.algorithm.loops.rgbd_verify import RgbdVerifier

    verifier = RgbdVerifier(pipeline.cfg.loop_closure.rgbd)
    fa, fb = verifier.features(source[a]), verifier.features(source[b])
    if fa is None or fb is None:
        return None, None
    edge = depth_agreement(fa, fb, np.linalg.inv(T_a_b), 0.03)[0]
    reference = depth_agreement(fa, fb, np.linalg.inv(truth), 0.03)[0]
    return edge, reference


def _pose_consistency(pipeline, source, gt: np.ndarray, gap: int = 20) -> dict[str, float]:
    """Median depth agreement of frame pairs ``(k, k + gap)`` under three sets of poses.

    Needs no ground truth: a relative pose under which the two depth images agree better is
    more consistent with the sensor. Reported for the ground truth, the odometry and the SLAM
    poses, so that a trajectory error against the ground truth can be put into proportion.
    """
    from slam.algorithm.loops.keyframes import depth_agreement
    from slam.algorithm.loops.rgbd_verify import RgbdVerifier

    verifier = RgbdVerifier(pipeline.cfg.loop_closure.rgbd)
    sets = {"gt": gt, "odometry": pipeline.odometry_poses(), "slam": pipeline.slam_poses()}
    values: dict[str, list[float]] = {name: [] for name in sets}
    for k in range(0, len(gt) - gap, gap):
        fa, fb = verifier.features(source[k]), verifier.features(source[k + gap])
        if fa is None or fb is None:
            continue
        for name, poses in sets.items():
            T_b_a = np.linalg.inv(poses[k + gap]) @ poses[k]
            values[name].append(depth_agreement(fa, fb, T_b_a, 0.03)[0])
    return {name: float(np.median(v)) if v else float("nan") for name, v in values.items()}


def _run(config_name: str, overrides: dict[str, Any], dataset: str) -> dict[str, Any]:
    from frontends.sources import make_source
    from slam.assembly.datasets import source_kwargs

    cfg = load_config(config_name, overrides)
    source = make_source(dataset, **source_kwargs(cfg))
    pipeline, wall = run_pipeline(cfg, source)
    gt = source.gt_poses
    out = trajectory_summary(pipeline, gt, wall)
    loops = []
    for c, (error_m, error_deg, kept) in zip(
        pipeline.accepted_loops(), out.pop("loop_errors"), strict=True
    ):
        a, b = anchor_frames(pipeline, c)
        truth = np.linalg.inv(gt[a]) @ gt[b]
        agreement_edge, agreement_gt = _depth_agreements(pipeline, source, a, b, c.T_Ai_Aj, truth)
        loops.append({"i": c.reference_id, "j": c.query_id, "frames": [int(a), int(b)],
                      "error_m": error_m, "error_deg": error_deg, "kept": kept,
                      "detector": c.detector, "depth_agreement_edge": agreement_edge,
                      "depth_agreement_gt": agreement_gt})  # fmt: skip
    out["loops"] = loops
    out["load_avg"] = list(os.getloadavg())
    out["pose_consistency"] = _pose_consistency(pipeline, source, gt)
    return out


SCENARIOS = {
    "7scenes": (
        "7-Scenes redkitchen seq-01 0-399",
        "7scenes",
        {"source": {"root": str(DATA / "7scenes_redkitchen"), "sequence": "seq-01"}},
        "7scenes",
    ),
    "room": ("generated room (demo config)", "demo", {}, "generated"),
}


def _cm(value: float) -> str:
    return f"{100 * value:.1f}"


def write_report(path: Path, saved: dict[str, Any]) -> None:
    lines = [
        "## Trajectory accuracy (RGB-D loops and odometry)",
        "",
        f"- Command: `{saved['command']}`",
        f"- Machine: {saved['machine']}",
        "- Every run: one process, `NullLogger`, map on the CPU, torch with 1 thread; frames/s is "
        "the whole pipeline. Load average = 1-min load average at the end of the run (a shared "
        "2-core machine: other jobs inflate wall times). ATE: RMSE after SE(3) Umeyama "
        "alignment without scale; per axis in the ground-truth frame. Depth agreement (needs no "
        "ground truth): median over frame pairs (k, k+20) of the fraction of frame k's depth "
        "pixels that, moved into frame k+20 by the pair's relative pose, agree with its depth "
        "within 3 cm; higher = more consistent with the sensor.",
        repeats_line(deterministic="Accuracy is the same in every run (deterministic)."),
        "",
        "| run | label | revision | ATE odometry [cm] | ATE SLAM [cm] | SLAM per axis x / y / z "
        "[cm] | loops verified / kept | loop error median [cm / deg] | loop error max "
        "[cm / deg] | depth agreement, frames k / k+20: GT / odometry / SLAM | frames/s | "
        "load avg |",
        "|---|---|---|---:|---:|---|---|---|---|---|---:|---:|",
    ]
    for key, (title, *_rest) in SCENARIOS.items():
        for label, runs in saved["runs"].items():
            r = runs.get(key)
            if r is None:
                continue
            if "unsupported" in r:
                lines.append(f"| {title} | {label} | {runs['_revision']} | {r['unsupported']} |")
                continue
            err = np.array([[e["error_m"], e["error_deg"]] for e in r["loops"]]).reshape(-1, 2)
            median = (
                f"{_cm(np.median(err[:, 0]))} / {np.median(err[:, 1]):.2f}" if len(err) else "-"
            )
            worst = f"{_cm(err[:, 0].max())} / {err[:, 1].max():.2f}" if len(err) else "-"
            axes = " / ".join(_cm(v) for v in r["ate_xyz_slam_m"])
            pc = r.get("pose_consistency")
            consistency = f"{pc['gt']:.3f} / {pc['odometry']:.3f} / {pc['slam']:.3f}" if pc else "-"
            lines.append(
                f"| {title} | {label} | {runs['_revision']} | {_cm(r['ate_odometry_m'])} | "
                f"{_cm(r['ate_slam_m'])} | {axes} | {r['verified']} / {r['kept']} | {median} | "
                f"{worst} | {consistency} | {r['fps']:.1f} | {r['load_avg'][0]:.1f} |"
            )
    lines += [
        "",
        "### Every loop edge against ground truth",
        "",
        "Error = the edge's relative pose of the two anchor frames vs the ground truth's. Depth "
        "agreement: fraction of the first keyframe's depth pixels (every 4th) that, moved into "
        "the second keyframe's view, agree with its depth within 3 cm, once with the edge and "
        "once with the ground-truth relative pose; it needs no ground truth, so where the edge "
        "agrees better than the ground truth, the error column measures the ground truth too.",
        "",
    ]
    for key, (title, *_rest) in SCENARIOS.items():
        for label, runs in saved["runs"].items():
            r = runs.get(key)
            if r is None or "unsupported" in r:
                continue
            rejected = ", ".join(f"{k}: {v}" for k, v in sorted(r["rejections"].items()))
            lines += [
                f"{title}, {label}: {r['candidates']} candidates, {r['verified']} verified, "
                f"{r['verified'] - r['kept']} rejected by the pose graph; candidates rejected by "
                f"the verifier, by first word of the reason: {rejected or 'none'}.",
                "",
            ]
            if not r["loops"]:
                continue
            lines += [
                "| edge i-j (frames) | found by | error [cm] | error [deg] | kept by graph | "
                "depth agreement: edge / ground truth |",
                "|---|---|---:|---:|---|---|",
            ]
            for e in r["loops"]:
                frames = "-".join(str(f) for f in e.get("frames", []))
                agreement = (
                    f"{e['depth_agreement_edge']:.2f} / {e['depth_agreement_gt']:.2f}"
                    if e.get("depth_agreement_gt") is not None
                    else "-"
                )
                lines.append(
                    f"| {e['i']}-{e['j']} ({frames}) | {e.get('detector', '')} | "
                    f"{_cm(e['error_m'])} | {e['error_deg']:.2f} | "
                    f"{'yes' if e['kept'] else 'no'} | {agreement} |"
                )
            lines.append("")
    write_text_atomic(path, "\n".join(lines) + "\n")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", metavar="REV", help="also run revision REV")
    parser.add_argument("--out", type=Path, default=RESULTS / "accuracy.md")
    parser.add_argument("--only", choices=sorted(SCENARIOS), action="append")
    parser.add_argument("--report-only", action="store_true")
    parser.add_argument(
        "--quick", action="store_true", help="the generated room only (run_all --quick)"
    )
    parser.add_argument(
        "--override",
        type=json.loads,
        default={},
        help="config overrides for every run, as JSON (e.g. '{\"pose_graph\": {...}}')",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s")
    log.setLevel(logging.INFO)
    raw = args.out.with_suffix(".json")
    if args.report_only:
        write_report(args.out, json.loads(raw.read_text()))
        return 0
    shown = sys.argv[1:] if argv is None else argv
    saved: dict[str, Any] = {
        "command": shlex.join(["python", "-m", "benchmarks.bench_accuracy", *shown]),
        "machine": machine_line(),
        "runs": {},
    }
    with contextlib.ExitStack() as stack:
        codes: dict[str, Path | None] = {}
        if args.before:
            codes["before"] = stack.enter_context(checkout(args.before))
        codes["after"] = None
        for label, code in codes.items():
            runs = saved["runs"].setdefault(label, {})
            runs["_revision"] = git_revision(code or REPO)
            runs["_date"] = dt.datetime.now().isoformat(timespec="seconds")
            for key in args.only or (["room"] if args.quick else sorted(SCENARIOS)):
                _title, config_name, overrides, dataset = SCENARIOS[key]
                if dataset == "7scenes" and not (DATA / "7scenes_redkitchen").is_dir():
                    log.warning("no 7-Scenes data under %s: skipped", DATA)
                    continue
                run_args = (config_name, merge_overrides(overrides, args.override), dataset)
                try:
                    runs[key] = r = repeat_runs(
                        lambda code=code, run_args=run_args: in_child(_run, *run_args, code=code),
                        ("wall_s", "fps"),
                    )
                except UnsupportedRevision as error:
                    runs[key] = {"unsupported": str(error)}
                    continue
                log.info(
                    "%s %s: ATE odometry %s cm, SLAM %s cm, loops verified/kept %d/%d, %.1f fps",
                    key,
                    label,
                    _cm(r["ate_odometry_m"]),
                    _cm(r["ate_slam_m"]),
                    r["verified"],
                    r["kept"],
                    r["fps"],
                )
    write_text_atomic(raw, json.dumps(saved, indent=2))
    write_report(args.out, saved)
    return 0


if __name__ == "__main__":
    sys.exit(main())
