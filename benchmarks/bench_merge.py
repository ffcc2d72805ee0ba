"""Multi-session merging: a sequence split in two sessions, each run on its own, merged without
the scans, against one run over the whole sequence.

    python -m benchmarks.bench_merge [--quick] [--scenario demo kitti00 7scenes generated-lidar]

Scenarios (:data:`SCENARIOS`): the generated room, the generated street along KITTI 00, the real
7-Scenes redkitchen seq-01 (skipped without ``../shared/data``) and the short generated street
loop; ``--quick`` runs demo (120 frames) and 7scenes. Per scenario: ``slam.run`` on the two halves
and on the whole; then, with the data folder taken away, ``slam.merge`` joins the two runs.
Reported: combined ATE against the full run's, inter-session loops and their error against the
ground truth, the merge's wall time (median of ``REPEATS``) and peak RSS, the session section's
bytes in ``map.npz``, the merged mesh against the raw points re-fused under the merged poses and
against the full run's mesh; then the second half as ``slam.run --map`` of the first: where it
was relocalised live and how far its live poses are from the merged ones. Writes
``benchmarks/results/merge.md`` and ``.json``.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.harness.child import run_module
from benchmarks.harness.cli import bench_parser, command_line
from benchmarks.harness.kitti import FULL, QUICK, have_kitti, kitti_root, kitti_source
from benchmarks.harness.machine import section_header
from benchmarks.harness.paths import DATA
from benchmarks.harness.repeat import REPEATS, Timing, repeats_line
from benchmarks.harness.results import cm, run_scenarios, scenario_arguments, write_results

SEVEN_SCENES = DATA / "7scenes_redkitchen"


@dataclass(frozen=True)
class Scenario:
    """One split sequence: the ``slam.run`` arguments and where its data comes from."""

    run_args: tuple[str, ...]
    frames: int
    quick_frames: int
    #: "generated": ``slam.run`` generates it into the work folder; "kitti": the benchmarks'
    #: cached KITTI 00 street (linked); "7scenes": the shared real frames (linked)
    data: str


SCENARIOS = {
    "demo": Scenario(("demo",), 240, 120, "generated"),
    "kitti00": Scenario(
        ("kitti", "00", "--set", "source.kitti.correct_vertical_angle=false"),
        FULL.num_frames,
        QUICK.num_frames,
        "kitti",
    ),
    "7scenes": Scenario(("7scenes", "seq-01"), 400, 400, "7scenes"),
    "generated-lidar": Scenario(("generated-lidar",), 150, 150, "generated"),
}


FULL_SCENARIOS = ("demo", "kitti00", "7scenes")
QUICK_SCENARIOS = ("demo", "7scenes")
"""--quick leaves out kitti00 (its 550-scan halves cost more than the quick budget allows)."""

KITTI_NOTE = (
    "the generated 64-beam street along the real KITTI 00 trajectory read by `slam.run kitti 00` "
    f"with configs/kitti.yaml (vertical-angle correction off, as the scans are ideal); quick: "
    f"{QUICK.describe()}, full: {FULL.describe()}. 7scenes: ground truth = the dataset's "
    "KinectFusion poses."
)


def _data_root(spec: Scenario, quick: bool) -> Path | None:
    """The folder to link as the scenario's data, None where ``slam.run`` generates it, or
    raise ``FileNotFoundError`` when the data is missing."""
    if spec.data == "generated":
        return None
    if spec.data == "7scenes":
        if not (SEVEN_SCENES / "seq-01").is_dir():
            raise FileNotFoundError(f"no 7-Scenes frames at {SEVEN_SCENES}")
        return SEVEN_SCENES
    if not have_kitti():
        raise FileNotFoundError("no KITTI 00 poses/calibration under ../shared/data/kitti")
    return kitti_root(kitti_source(quick))


def _session_bytes(map_path: Path) -> int:
    import zipfile

    with zipfile.ZipFile(map_path) as z:
        return sum(i.compress_size for i in z.infolist() if i.filename.startswith("session_"))


def _loop_errors(merged: Path, gt: np.ndarray) -> list[dict[str, float]]:
    """Error of every kept inter-session edge against the ground truth of its anchor frames."""
    from common.geometry import relative_motion
    from mapping.map_io import load_session
    from slam.algorithm.merge.session import SessionRecord

    _, header, arrays = load_session(merged / "map.npz")
    session = SessionRecord.from_arrays(header, arrays)
    anchor_row = {}
    for row, node in enumerate(session.frame_submap.tolist()):
        anchor_row.setdefault(node, row)
    part_of = np.zeros(len(session.frame_submap), dtype=int)
    for k, part in enumerate(session.parts):
        part_of[part["first_row"] : part["first_row"] + part["rows"]] = k
    M = session.dataset_mirror
    errors = []
    for e in session.loops:
        ri, rj = anchor_row[e.i], anchor_row[e.j]
        if part_of[ri] == part_of[rj]:
            continue
        truth = M @ np.linalg.inv(gt[ri]) @ gt[rj] @ M
        t, r = relative_motion(truth, e.T_Ai_Aj)
        errors.append({"i": e.i, "j": e.j, "translation_m": t, "rotation_deg": r})
    return errors


def _refused_map(merged: Path, data_cfg: Path) -> Any:
    """The raw frames re-fused under the merged poses: the run's own keyframer groups them into
    submaps (same ranges, voxels, normals) and every submap is encoded at its merged anchor pose;
    no remapping is involved, so this is the map remapping must match."""
    from slam.algorithm.submaps import Keyframer
    from slam.assembly.builders import build_map, build_source
    from slam.assembly.config import load_run_config
    from slam.run_folder.trajectory_io import read_kitti

    cfg = load_run_config(data_cfg)
    cfg.source.frames = None
    source = build_source(cfg)
    poses = source.to_dataset_frame(read_kitti(merged / "poses_slam.kitti.txt"))
    neural_map = build_map(cfg)
    keyframer = Keyframer(cfg.submaps)

    def fuse(record) -> None:
        if record is not None and len(record.points_A):
            T_W_A = poses[record.frame_indices[0]]
            neural_map.fuse(neural_map.encode(record.submap_id, record.points_A,
                                              record.normals_A, T_W_A))  # fmt: skip

    for index in range(len(poses)):
        closed, _, _ = keyframer.add(source[index], poses[index])
        fuse(closed)
    fuse(keyframer.finish())
    return neural_map.extract_mesh()


def _mesh_distance(a, b) -> dict[str, float]:
    import trimesh

    from slam.evaluation.metrics.mesh import surface_distances

    pa = trimesh.sample.sample_surface(a, 50_000, seed=1)[0]
    pb = trimesh.sample.sample_surface(b, 50_000, seed=2)[0]
    ab, ba = surface_distances(pa, b), surface_distances(pb, a)
    return {"a_to_b_m": float(np.mean(ab)), "b_to_a_m": float(np.mean(ba)),
            "symmetric_m": float((np.mean(ab) + np.mean(ba)) / 2)}  # fmt: skip


def scenario(name: str, quick: bool, work: Path) -> dict[str, Any]:
    import trimesh

    spec = SCENARIOS[name]
    n = spec.quick_frames if quick else spec.frames
    data = work / "data"
    source_root = _data_root(spec, quick)
    if source_root is not None:
        data.symlink_to(source_root, target_is_directory=True)
    common = ["--root", str(data), "--no-viz", "--no-progress"]
    if spec.data == "generated":
        common += ["--set", f"generated.num_frames={n}"]
    out: dict[str, Any] = {"frames": n, "split": n // 2}
    runs = {"full": f"0:{n}", "a": f"0:{n // 2}", "b": f"{n // 2}:{n}"}
    for key, frames in runs.items():
        wall, rss = run_module("slam.run", [*spec.run_args, "--frames", frames, *common,
                                        "--out", str(work / key)], work / f"{key}.log")  # fmt: skip
        metrics = json.loads((work / key / "metrics.json").read_text())
        out[key] = {"wall_s": wall, "peak_rss_mb": rss,
                    "ate_m": metrics["trajectory"]["slam"]["ate_rmse_m"],
                    "map_bytes": (work / key / "map.npz").stat().st_size,
                    "session_bytes": _session_bytes(work / key / "map.npz")}  # fmt: skip
    backup = work / "data-kept"
    shutil.move(data, backup)  # the merge runs without the scans
    try:
        merges = [run_module("slam.merge", [str(work / "a"), str(work / "b"), "--out",
                                        str(work / f"merged-{k}")], work / f"merge-{k}.log")
                  for k in range(REPEATS)]  # fmt: skip
    finally:
        shutil.move(backup, data)
    (work / "merged-0").rename(work / "merged")
    merged = json.loads((work / "merged" / "metrics.json").read_text())
    gt = np.concatenate([np.loadtxt(work / k / "poses_gt.kitti.txt").reshape(-1, 3, 4)
                         for k in ("a", "b")])  # fmt: skip
    gt = np.concatenate([gt, np.tile([[[0, 0, 0, 1.0]]], (len(gt), 1, 1))], axis=1)
    out["merge"] = {"wall_s": [wall for wall, _ in merges], "peak_rss_mb": merges[0][1],
                    "combined_ate_m": merged.get("combined_ate_rmse_m"),
                    "inter_candidates": merged["inter_session_candidates"],
                    "inter_kept": merged["inter_session_loops_kept"],
                    "loop_errors": _loop_errors(work / "merged", gt),
                    "seconds": merged["seconds"]}  # fmt: skip
    merged_mesh = trimesh.load(work / "merged" / "mesh.ply", force="mesh")
    full_mesh = trimesh.load(work / "full" / "mesh.ply", force="mesh")
    refused = _refused_map(work / "merged", work / "full" / "config.yaml")
    out["mesh_vs_refused"] = _mesh_distance(merged_mesh, refused)
    out["mesh_vs_full_run"] = _mesh_distance(merged_mesh, full_mesh)
    out["continued"] = _continued(spec, runs["b"], common, work)
    return out


def _continued(spec, frames: str, common: list[str], work: Path) -> dict[str, Any]:
    """Session B again, as ``slam.run --map A``: where it was relocalised live, how far its
    live poses (in its own run folder) are from where the final merge puts them, and the
    continued map's combined ATE."""
    from slam.run_folder.trajectory_io import read_kitti

    out_dir = work / "continued"
    wall, rss = run_module("slam.run", [*spec.run_args, "--frames", frames, *common, "--map",
                                    str(work / "a"), "--out", str(out_dir)],
                       work / "continued.log")  # fmt: skip
    live = json.loads((out_dir / "session" / "metrics.json").read_text())["relocalisation"]
    merged = json.loads((out_dir / "metrics.json").read_text())
    own = read_kitti(out_dir / "session" / "poses_slam.kitti.txt")
    final = read_kitti(out_dir / "poses_slam.kitti.txt")[-len(own) :]
    gap = np.linalg.norm(own[:, :3, 3] - final[:, :3, 3], axis=1)
    return {"wall_s": wall, "peak_rss_mb": rss, "relocalised": live["relocalised"],
            "frames": len(own),
            "submap_frames": live.get("submap_frames"), "submaps_tried": live["submaps_tried"],
            "live_vs_merged_max_m": float(gap.max()), "live_vs_merged_mean_m": float(gap.mean()),
            "combined_ate_m": merged.get("combined_ate_rmse_m")}  # fmt: skip


def report(results: dict[str, Any], command: str) -> str:
    lines = [*section_header("Multi-session merge", command),
             "- Two sessions (first and second half of one sequence), each run on its own; the "
             "data folder is taken away before `slam.merge` runs. kitti00: "
             + KITTI_NOTE,
             repeats_line("Only `slam.merge` is repeated; the SLAM runs (deterministic) run "
                          "once, their speed is bench_accuracy's and bench_throughput's. "
                          "--quick: demo and 7scenes only."), ""]  # fmt: skip
    for name, r in results.items():
        if "skipped" in r:
            lines += [f"### {name}", "", f"Skipped: {r['skipped']}.", ""]
            continue
        m = r["merge"]
        errors = m["loop_errors"]
        err_t = max((e["translation_m"] for e in errors), default=None)
        err_r = max((e["rotation_deg"] for e in errors), default=None)
        a = r["a"]
        lines += [
            f"### {name} ({r['frames']} frames: sessions 0-{r['split'] - 1} and "
            f"{r['split']}-{r['frames'] - 1})", "",
            "| | value |", "|---|---:|",
            f"| ATE full run [cm] | {cm(r['full']['ate_m'], 2)} |",
            f"| ATE session A / B alone [cm] | {cm(a['ate_m'], 2)} / {cm(r['b']['ate_m'], 2)} |",
            f"| combined ATE after merge [cm] | {cm(m['combined_ate_m'], 2)} |",
            f"| merged / full ATE | {m['combined_ate_m'] / r['full']['ate_m']:.2f} |",
            f"| inter-session candidates / kept | {m['inter_candidates']} / {m['inter_kept']} |",
            f"| worst kept inter-session edge vs truth [cm / deg] | {cm(err_t, 2)} / "
            f"{'-' if err_r is None else f'{err_r:.2f}'} |",
            f"| merge wall [s] | {Timing(m['wall_s']):.1f} |",
            f"| peak RSS of the merge / of the full SLAM run [MB] | {m['peak_rss_mb']:.0f} / "
            f"{r['full']['peak_rss_mb']:.0f} |",
            f"| session section / map.npz (session A) [kB] | {a['session_bytes'] / 1e3:.0f} / "
            f"{a['map_bytes'] / 1e3:.0f} ({100 * a['session_bytes'] / a['map_bytes']:.1f} %) |",
            f"| merged mesh vs raw points re-fused under merged poses [cm] | "
            f"{cm(r['mesh_vs_refused']['symmetric_m'], 2)} |",
            f"| merged mesh vs full run's mesh [cm] | "
            f"{cm(r['mesh_vs_full_run']['symmetric_m'], 2)} |",
            *_continued_rows(r["continued"]),
            "",
        ]  # fmt: skip
    return "\n".join(lines) + "\n"


def _continued_rows(c: dict[str, Any]) -> list[str]:
    placed = f"not placed ({c['submaps_tried']} submaps tried)"
    if c["relocalised"]:
        placed = (
            f"frames {c['submap_frames'][0]}-{c['submap_frames'][1]} of its {c['frames']} "
            f"({c['submaps_tried']} submap(s) tried)"
        )
    return [
        f"| `--map A` on session B: relocalised live by | {placed} |",
        f"| `--map A`: live poses vs merged, mean / max [cm] | "
        f"{cm(c['live_vs_merged_mean_m'], 2)} / {cm(c['live_vs_merged_max_m'], 2)} |",
        f"| `--map A`: combined ATE [cm] / peak RSS [MB] | "
        f"{cm(c['combined_ate_m'], 2)} / {c['peak_rss_mb']:.0f} |",
    ]


def build_parser():
    parser = bench_parser(__doc__, "shorter sequences")
    scenario_arguments(parser, sorted(SCENARIOS), "demo kitti00 7scenes (--quick: demo 7scenes)")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    names = args.scenario or (QUICK_SCENARIOS if args.quick else FULL_SCENARIOS)
    results = run_scenarios(
        names, lambda name, work: scenario(name, args.quick, work), "merge", args.work
    )
    write_results("merge", results, report(results, command_line("bench_merge", argv)))


if __name__ == "__main__":
    main()
