"""The report's "History" section: one link and one line per archived run, nothing inlined.

``benchmarks/archive/`` keeps what an invocation of ``run_all`` does not measure again: the
full-length runs (longer than a quick invocation allows) and the report as it stood before the
one-command harness. Each file states its own command, revision, date and machine;
tests/test_benchmarks.py keeps :data:`ARCHIVED` in step with the files.
"""

from __future__ import annotations

from pathlib import Path

from benchmarks.harness.paths import REPO

ARCHIVE_DIR = REPO / "benchmarks" / "archive"
FULL_RUNS = "full-runs"

ARCHIVED: dict[str, str] = {
    "until-df1b174/BENCHMARKS.md": "the report before the one-command harness (sections of "
    "different days and revisions, up to df1b174), with the accuracy, keyframing and throughput "
    "histories beside it",
    "full-runs/merge-kitti00.md": "multi-session merge on the generated KITTI 00 street split at "
    "frame 2270, merged without the scans, and the second half relocalised live",
    "full-runs/real.md": "real scans: all 331 MulRan keyframes and the KITTI raw drive (the "
    "README's real-scan figures)",
    "full-runs/rgbd-memory.md": "RGB-D memory and frames/s of the demo and 7-Scenes 0-399 before "
    "and after the compact kept keyframes, with a per-object breakdown",
    "full-runs/slam-7scenes.md": "7-Scenes redkitchen 0-399: every verified loop edge judged "
    "against a dense depth registration (a check since removed; the accuracy section's depth "
    "agreement asks the same of every loop edge)",
    "full-runs/throughput-1000.md": "1,000 scans, the submap worker against the code before it",
    "full-runs/throughput-4541.md": "all 4,541 scans: wall, CPU, peak RSS and RSS growth of ours, "
    "KISS-ICP alone and KISS-SLAM, before and after KISS-ICP moved to a child process",
    "full-runs/throughput-4541-loop-refine.md": "all 4,541 scans: the cost of the point-to-plane "
    "KISS-ICP start and the loop ICP refinements",
    "full-runs/throughput-4541-loop-cost.md": "all 4,541 scans: thinned coarse loop ICP passes "
    "and a 32-frame submap queue against the code before them",
    "full-runs/throughput-4541-cpu-floor.md": "all 4,541 scans: ours' CPU floor on 2 cores "
    "against KISS-SLAM's wall",
    "full-runs/throughput-4541-cheap-map.md": "all 4,541 scans with a cheaper map (a third of "
    "the points, 1 m mesh lattice): not faster, rejected",
    "full-runs/throughput-4541-kiss-1-thread.md": "all 4,541 scans with KISS-ICP on one thread: "
    "slower, rejected",
    "full-runs/throughput_profile-1000.md": "where the CPU time of a 1,000-scan run goes (profile)",
    "full-runs/throughput_profile-4541.md": "where the CPU time of the 4,541-scan run goes "
    "(profile)",
    "full-runs/variants-quick.md": "every LiDAR data variant on the quick window, with and "
    "without the point-to-plane start and loop ICP refinements, KISS-SLAM beside",
    "full-runs/variants-quick-loop-cost.md": "every data variant on the quick window: cheaper "
    "loop ICP against the full-density passes",
    "full-runs/variants-4541.md": "standard street and KITTI angle correction at full length",
    "full-runs/variants-4541-sparse.md": "the sparse street at full length: a far-off kept loop "
    "the quick window did not show",
    "full-runs/variants-4541-sparse-after.md": "the sparse street at full length after the loop "
    "ICP refinements",
    "full-runs/variants-4541-all.md": "every data variant at full length in one table, with "
    "targets",
    "before-after/rerun-rates.md": "the pipeline's rate with the default recording against "
    "--no-viz, before (2eec4f2) and after the executor",
    "before-after/reliability-maps.md": "crafted map files, self-merges, racing and stopped "
    "merges, --map of another sensor: before (a9b0bc8) and after untrusted-map loading",
    "before-after/reliability-commands.md": "slam.eval bounds, config bounds, --rrd, --serve "
    "ports, RERUN=off: before (a9b0bc8) and after",
    "before-after/lidar-map-range.md": "LiDAR map quality against a 0.2 m TSDF: the KITTI map "
    "to 30 m (before) and to 80 m, coarser far points and 0.6 m voxels, on 150 scans",
}
"""Archived report files (relative to :data:`ARCHIVE_DIR`) and what each measured."""


def archived_files(archive_dir: Path = ARCHIVE_DIR) -> list[str]:
    """The report files in ``archive_dir`` (``.md`` but the READMEs), relative to it."""
    return sorted(
        str(path.relative_to(archive_dir))
        for path in archive_dir.rglob("*.md")
        if path.name != "README.md"
    )


def history_lines(link_prefix: str = "benchmarks/archive") -> list[str]:
    """The "History" section: a Markdown link and one line per archived file."""
    lines = [
        "## History",
        "",
        "Earlier and full-length runs, not part of this invocation; each file names its own "
        "command, revision, date and machine (why each was kept: "
        f"[{FULL_RUNS}/README.md]({link_prefix}/{FULL_RUNS}/README.md)).",
        "",
    ]
    lines += [f"- [{name}]({link_prefix}/{name}): {what}" for name, what in ARCHIVED.items()]
    return [*lines, ""]
