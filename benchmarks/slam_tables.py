"""Markdown tables of ``bench_slam`` results."""

from __future__ import annotations

import numpy as np


def fmt(value, unit: str = "", digits: int = 3) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        return f"{value:.{digits}f}{unit}"
    return f"{value}{unit}"


def cm(value) -> str:
    return "n/a" if value is None else f"{100 * value:.2f}"


def false_loops(r: dict, false_m: float, false_deg: float) -> tuple[int, int]:
    """Verified loops (and those the graph kept) whose pose is off by more than the limits."""
    wrong = [m > false_m or d > false_deg for m, d in r["loop_errors"]]
    return sum(wrong), sum(w and k for w, k in zip(wrong, r["loop_kept"], strict=True))


def trajectory_table(rows: list[tuple[str, dict, tuple[float, float]]]) -> list[str]:
    lines = [
        "| run | frames | submaps | loop candidates | verified | kept by graph | false verified "
        "/ kept vs ground truth (limit) | median loop error vs ground truth [cm / deg] | "
        "ATE odometry [m] | ATE SLAM [m] | "
        "ATE x / y / z odometry -> SLAM [m] | frames/s | peak RSS [MB] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def axes(r: dict) -> str:
        if "ate_xyz_slam_m" not in r:  # results saved before the per-axis split
            return "n/a"
        odometry, slam = (
            " / ".join(f"{v:.3f}" for v in r[k]) for k in ("ate_xyz_odometry_m", "ate_xyz_slam_m")
        )
        return f"{odometry} -> {slam}"

    for name, r, (false_m, false_deg) in rows:
        wrong, wrong_kept = false_loops(r, false_m, false_deg)
        errors = np.array(r["loop_errors"]).reshape(-1, 2)
        median = (
            f"{100 * np.median(errors[:, 0]):.1f} / {np.median(errors[:, 1]):.2f}"
            if len(errors)
            else "n/a"
        )
        lines.append(
            f"| {name} | {r['frames']} | {r['submaps']} | {r['candidates']} | {r['verified']} | "
            f"{r['kept']} | {wrong} / {wrong_kept} ({100 * false_m:.0f} cm, {false_deg:.0f} deg) | "
            f"{median} | {r['ate_odometry_m']:.3f} | {r['ate_slam_m']:.3f} | {axes(r)} | "
            f"{r['fps']:.2f} | "
            f"{r['peak_rss_mb']:.0f} |"
        )
    return lines


def remap_table(rows: list[tuple[str, dict]]) -> list[str]:
    lines = [
        "| run | remap passes | submap moves | frames moved | total [s] | max per pass [s] | "
        "submaps/s | frames/s (paper: 50) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, r in rows:
        seconds = r["remap_s_total"]
        sub_rate = r["remap_moved"] / seconds if seconds > 0 else None
        frame_rate = r["remap_frames_moved"] / seconds if seconds > 0 else None
        lines.append(
            f"| {name} | {r['remap_events']} | {r['remap_moved']} | {r['remap_frames_moved']} | "
            f"{seconds:.2f} | {r['remap_s_max']:.2f} | {fmt(sub_rate, digits=1)} | "
            f"{fmt(frame_rate, digits=1)} |"
        )
    return lines


def stage_table(rows: list[tuple[str, dict]]) -> list[str]:
    stages = ["odometry", "keyframing", "mapping", "loop_detection", "pose_graph", "remap"]
    lines = [
        "| run | " + " | ".join(stages) + " | whole run |",
        "|---|" + "---|" * (len(stages) + 1),
    ]
    for name, r in rows:
        cells = [fmt(r["stage_s"].get(s, 0.0), digits=1) for s in stages]
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {r['wall_s']:.1f} |")
    return lines


DENSE_LIMIT = (0.02, 1.0)
"""An RGB-D loop edge counts as off beyond 2 cm / 1 deg from the dense depth registration (the
registration's own spread between starts and directions stays below that; see dense_section)."""


def _pair(value: list[float]) -> str:
    return f"{100 * value[0]:.2f} / {value[1]:.2f}"


def _worst(edges: list[dict], key: str) -> str:
    if not edges:
        return "n/a"
    worst = max(edges, key=lambda e: (e[key][0] / DENSE_LIMIT[0], e[key][1] / DENSE_LIMIT[1]))
    return _pair(worst[key])


def _beyond(edges: list[dict], key: str, limit: tuple[float, float]) -> int:
    return sum(1 for e in edges if e[key][0] > limit[0] or e[key][1] > limit[1])


def dense_section(name: str, r: dict) -> list[str]:
    """RGB-D loop edges against a dense depth registration of their anchor keyframes."""
    edges = r.get("loop_dense")
    if edges is None:
        return []
    kept = [e for e in edges if e["kept"]]
    limit_m, limit_deg = DENSE_LIMIT
    spread_keys = ("from_edge_vs_dense", "reverse_vs_dense")
    spread_m = max((e[k][0] for e in edges for k in spread_keys), default=float("nan"))
    spread_deg = max((e[k][1] for e in edges for k in spread_keys), default=float("nan"))
    identity_off = sum(
        1 for e in edges if e["from_identity_vs_dense"][0] > limit_m or not e["dense_ok"]
    )
    apart_m = (
        min((e["baseline"][0] for e in edges), default=float("nan")),
        max((e["baseline"][0] for e in edges), default=float("nan")),
    )
    apart_deg = max((e["baseline"][1] for e in edges), default=float("nan"))
    median = (
        f"{100 * np.median([e['edge_vs_dense'][0] for e in edges]):.2f} / "
        f"{np.median([e['edge_vs_dense'][1] for e in edges]):.2f}"
        if edges
        else "n/a"
    )
    lines = [
        "",
        f"#### {name}: loop edges against a dense depth registration",
        "",
        "The dataset's poses come from KinectFusion and are not what the depth images say at a "
        "revisit, so every verified loop edge is also judged against an independent dense depth "
        "registration of its two anchor keyframes (benchmarks/harness/depth_registration.py): "
        "OpenCV 5's `cv2.Odometry` with `OdometryType_DEPTH` (projective point-to-plane ICP, "
        "depth only, as 7-Scenes colour is not registered to depth), depth as the source reads "
        "it (mm / 1000, 0 and 65535 invalid, 0.1-4 m), started from the KinectFusion relative "
        "pose by warping the reference depth into the query view and re-warping from each "
        "result until the correction vanishes. Its own spread: started from the edge instead, "
        "or with the two frames' roles swapped, it lands at most "
        f"{100 * spread_m:.2f} cm / {spread_deg:.2f} deg from the run started from KinectFusion "
        f"(per edge below), hence the limit of {100 * limit_m:.0f} cm / {limit_deg:.0f} deg "
        "for an edge that disagrees with the depth. Started from identity it does not reach "
        f"the loop pose ({identity_off} of {len(edges)} edges end beyond the limit): the "
        f"anchors are {apart_m[0]:.2f}-{apart_m[1]:.2f} m and up to {apart_deg:.0f} deg apart, "
        "beyond its basin. Fit: of the "
        "reference depth pixels (every 2nd) moved into the query view that land on valid "
        "depth, the fraction within 2 cm and their RMS depth difference.",
        "",
        "| run | verified | kept | worst kept loop vs dense registration [cm / deg] | median "
        "vs dense [cm / deg] | beyond "
        f"{100 * limit_m:.0f} cm / {limit_deg:.0f} deg of dense: verified / kept | worst kept "
        "vs KinectFusion [cm / deg] | dense registration vs KinectFusion, median [cm / deg] |",
        "|---|---|---|---|---|---|---|---|",
        f"| {name} | {len(edges)} | {len(kept)} | {_worst(kept, 'edge_vs_dense')} | {median} | "
        f"{_beyond(edges, 'edge_vs_dense', DENSE_LIMIT)} / "
        f"{_beyond(kept, 'edge_vs_dense', DENSE_LIMIT)} | {_worst(kept, 'edge_vs_gt')} | "
        + (
            f"{100 * np.median([e['dense_vs_gt'][0] for e in edges]):.2f} / "
            f"{np.median([e['dense_vs_gt'][1] for e in edges]):.2f} |"
            if edges
            else "n/a |"
        ),
        "",
        "| submaps ref -> query (frames) | kept | anchors apart [m / deg] | edge vs dense [cm / "
        "deg] | edge vs KinectFusion [cm / deg] | dense vs KinectFusion [cm / deg] | fit of dense; "
        "edge; KinectFusion [% within 2 cm / RMS mm] | dense from the edge; roles swapped, vs "
        "dense [cm / deg] |",
        "|---|---|---|---|---|---|---|---|",
    ]

    def fit(value: list[float]) -> str:
        return f"{100 * value[0]:.0f} / {1000 * value[1]:.1f}"

    for e in edges:
        ok = "" if e["dense_ok"] else " (OpenCV: failed)"
        lines.append(
            f"| {e['reference_submap']} -> {e['query_submap']} ({e['reference_frame']}, "
            f"{e['query_frame']}) | {'yes' if e['kept'] else 'no'} | {e['baseline'][0]:.2f} / "
            f"{e['baseline'][1]:.0f} | {_pair(e['edge_vs_dense'])}{ok} | {_pair(e['edge_vs_gt'])}"
            f" | {_pair(e['dense_vs_gt'])} | {fit(e['dense_fit'])}; {fit(e['edge_fit'])}; "
            f"{fit(e['gt_fit'])} | {_pair(e['from_edge_vs_dense'])}; "
            f"{_pair(e['reverse_vs_dense'])} |"
        )
    return lines
