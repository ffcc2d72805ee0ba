"""Trajectory accuracy of the RGB-D pipeline and of every loop edge against ground truth.

    python -m benchmarks.bench_accuracy [--before REV] [--quick] [--out FILE.md]
    python -m benchmarks.bench_accuracy --report-only

Runs, each in its own process (``NullLogger``, map on the CPU, one torch thread): 7-Scenes
redkitchen seq-01 frames 0-399 with configs/7scenes.yaml (skipped without ../shared/data) and
the generated RGB-D room with configs/demo.yaml. ``--before REV`` runs them also at REV, checked
out beside this tree, into the same table. Every verified loop edge is listed with its error
against the ground truth and whether the pose graph kept it.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.harness.checkout import revisions
from benchmarks.harness.child import UnsupportedRevision, in_child
from benchmarks.harness.cli import bench_parser, command_line
from benchmarks.harness.machine import git_revision, machine_line
from benchmarks.harness.paths import DATA, REPO, RESULTS_DIR
from benchmarks.harness.pipeline import anchor_frames, load_config, run_pipeline, trajectory_summary
from benchmarks.harness.repeat import repeat_runs, repeats_line, restore_all
from benchmarks.harness.results import cm, table
from common.atomic_io import write_text_atomic
from slam.assembly.config import merge_overrides

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
    """Median depth agreement of frame pairs ``(k, k + gap)`` under the ground-truth, odometry
    and SLAM poses: how consistent each is with the sensor, with no ground truth needed."""
    from slam.algorithm.loops.keyframes import depth_agreement
    from slam.algorithm.loops.rgbd_verify import RgbdVerifier

    verifier = RgbdVerifier(pipeline.cfg.loop_closure.rgbd)
    sets = {"gt": gt, "odometry": pipeline.frames.odometry_poses(), "slam": pipeline.slam_poses()}
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
"""Per scenario: its title, config, overrides and dataset."""


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
    ]
    rows = []
    for key, (title, *_rest) in SCENARIOS.items():
        for label, runs in saved["runs"].items():
            r = runs.get(key)
            if r is None:
                continue
            if "unsupported" in r:
                rows.append([title, label, runs["_revision"], r["unsupported"]])
                continue
            err = np.array([[e["error_m"], e["error_deg"]] for e in r["loops"]]).reshape(-1, 2)
            median = worst = "-"
            if len(err):
                median = f"{cm(np.median(err[:, 0]))} / {np.median(err[:, 1]):.2f}"
                worst = f"{cm(err[:, 0].max())} / {err[:, 1].max():.2f}"
            pc = r.get("pose_consistency")
            consistency = f"{pc['gt']:.3f} / {pc['odometry']:.3f} / {pc['slam']:.3f}" if pc else "-"
            rows.append(
                [
                    title,
                    label,
                    runs["_revision"],
                    cm(r["ate_odometry_m"]),
                    cm(r["ate_slam_m"]),
                    " / ".join(cm(v) for v in r["ate_xyz_slam_m"]),
                    f"{r['verified']} / {r['kept']}",
                    median,
                    worst,
                    consistency,
                    f"{r['fps']:.1f}",
                    f"{r['load_avg'][0]:.1f}",
                ]
            )
    header = (
        "run | label | revision | ATE odometry [cm] | ATE SLAM [cm] | SLAM per axis "
        "x / y / z [cm] | loops verified / kept | loop error median [cm / deg] | loop error "
        "max [cm / deg] | depth agreement, frames k / k+20: GT / odometry / SLAM | "
        "frames/s | load avg"
    )
    lines += table(header, rows, "lllrrlllllrr")
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
            rows = []
            for e in r["loops"]:
                agreement = "-"
                if e.get("depth_agreement_gt") is not None:
                    agreement = f"{e['depth_agreement_edge']:.2f} / {e['depth_agreement_gt']:.2f}"
                frames = "-".join(str(f) for f in e.get("frames", []))
                rows.append(
                    [
                        f"{e['i']}-{e['j']} ({frames})",
                        e.get("detector", ""),
                        cm(e["error_m"]),
                        f"{e['error_deg']:.2f}",
                        "yes" if e["kept"] else "no",
                        agreement,
                    ]
                )
            header = (
                "edge i-j (frames) | found by | error [cm] | error [deg] | kept by graph | "
                "depth agreement: edge / ground truth"
            )
            lines += [*table(header, rows, "llrrll"), ""]
    write_text_atomic(path, "\n".join(lines) + "\n")


def build_parser():
    parser = bench_parser(
        __doc__, "the generated room only", before=True, out=RESULTS_DIR / "accuracy.md"
    )
    parser.add_argument("--only", choices=sorted(SCENARIOS), action="append")
    parser.add_argument("--report-only", action="store_true")
    parser.add_argument(
        "--override", type=json.loads, default={}, help="config overrides for every run, as JSON"
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s")
    log.setLevel(logging.INFO)
    raw = args.out.with_suffix(".json")
    if args.report_only:
        write_report(args.out, restore_all(json.loads(raw.read_text())))
        return 0
    saved = {"command": command_line("bench_accuracy", argv), "machine": machine_line(), "runs": {}}
    with revisions(args.before, "before") as codes:
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
                    cm(r["ate_odometry_m"]),
                    cm(r["ate_slam_m"]),
                    r["verified"],
                    r["kept"],
                    r["fps"],
                )
    write_text_atomic(raw, json.dumps(saved, indent=2))
    write_report(args.out, saved)
    return 0


if __name__ == "__main__":
    sys.exit(main())
