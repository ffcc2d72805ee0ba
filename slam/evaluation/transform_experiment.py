"""The paper's transform experiment ("two paths", RA-L 2022 Fig. 9): is transforming a neural map
as good as encoding the transformed points?

    python -m slam.eval transform [--dataset demo] [--sequence SEQ] [--root DIR]
        [--frames A:B:STEP] [--every 20] [--max-frames 12] [--variants first-order,zeroth-order]

For each selected frame with a ground-truth pose ``T_W_S`` (the frame's points ``P`` in the sensor
frame with normals, range-limited; RGB-D depth is read at full resolution,
``source.depth.stride=1``, unless ``--set`` says otherwise):

- encode-transform (the paper's contribution): encode ``P`` at the identity, then move the map to
  ``T_W_S`` with :meth:`mapping.neural_map.NeuralMap.move` (one map per *variant* of the transform
  settings: ``first-order`` = the configured transform, ``zeroth-order`` = without the Jacobian
  correction, ``uniform`` = near-uniform blending as the released code);
- transform-encode (the reference): encode ``T_W_S P`` directly.

Both maps are meshed; accuracy is the mean distance from the encode-transform mesh to the
transform-encode mesh, completion the reverse, and the completion ratio the fraction of reference
samples within 5 cm (``slam.evaluation.metrics.mesh.mesh_metrics``). Per-frame numbers go to
``results.json``; their distributions to ``transform_distributions.png`` and ``summary.md``.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

logger = logging.getLogger("slam.evaluation.transform_experiment")

VARIANTS: dict[str, dict[str, Any]] = {
    "first-order": {},
    "zeroth-order": {"transform_use_jacobian": False},
    "uniform": {"transform_use_jacobian": False, "transform_weighting": "uniform"},
}
DEFAULT_VARIANTS = ("first-order", "zeroth-order")


def frame_points(frame, submap_cfg) -> tuple[np.ndarray, np.ndarray]:
    """Points and unit normals of a frame in its sensor frame: range-limited like a submap's,
    normals estimated (towards the sensor) when the source has none.

    The points are not averaged on the submap grid: a single frame is much sparser than a submap,
    and averaging it would leave too few points per voxel for the encoder's pruning
    (``mapping.min_points_per_voxel``).
    """
    from common.normals import estimate_normals

    points = np.asarray(frame.points, dtype=np.float64)
    distance = np.linalg.norm(points, axis=1)
    keep = (distance >= submap_cfg.min_range_m) & (distance <= submap_cfg.max_range_m)
    points = points[keep]
    if frame.normals is not None:
        normals = np.asarray(frame.normals, dtype=np.float64)[keep]
    else:
        normals, _ = estimate_normals(
            points, np.zeros(3), num_neighbours=submap_cfg.normal_neighbours
        )
    norm = np.linalg.norm(normals, axis=1)
    good = norm > 0.5
    return points[good], normals[good] / norm[good, None]


def two_paths(
    points_S: np.ndarray,
    normals_S: np.ndarray,
    T_W_S: np.ndarray,
    map_cfg,
    model,
    *,
    variants: Sequence[str] = DEFAULT_VARIANTS,
    num_samples: int = 50_000,
) -> dict[str, dict[str, float]]:
    """Mesh accuracy/completion of encode-transform (per variant) against transform-encode."""
    from mapping.neural_map import NeuralMap
    from slam.evaluation.metrics.mesh import mesh_metrics

    reference = NeuralMap(map_cfg, model=model)
    reference.fuse(reference.encode(0, points_S, normals_S, T_W_S))
    reference_mesh = reference.extract_mesh()
    if len(reference_mesh.faces) == 0:
        raise ValueError("the transform-encode map has no surface (too few points)")
    results: dict[str, dict[str, float]] = {}
    for name in variants:
        moved = NeuralMap(map_cfg.model_copy(update=VARIANTS[name]), model=model)
        submap = moved.encode(0, points_S, normals_S, np.eye(4))
        moved.fuse(submap)
        start = time.perf_counter()
        moved.move(submap, T_W_S)
        move_s = time.perf_counter() - start
        mesh = moved.extract_mesh()
        metrics = mesh_metrics(mesh, reference_mesh, num_samples=num_samples).as_dict()
        metrics["move_s"] = move_s
        metrics["num_reference_faces"] = len(reference_mesh.faces)
        results[name] = metrics
    return results


def run_transform_experiment(
    source,
    cfg,
    *,
    every: int = 20,
    max_frames: int = 12,
    variants: Sequence[str] = DEFAULT_VARIANTS,
    num_samples: int = 50_000,
) -> list[dict[str, Any]]:
    """The experiment on every ``every``-th frame of ``source`` (at most ``max_frames``)."""
    from mapping.neural_map import NeuralMap

    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        raise ValueError(f"unknown transform variants {unknown}; choose from {sorted(VARIANTS)}")
    model = NeuralMap(cfg.mapping).model
    rows: list[dict[str, Any]] = []
    for index in range(0, len(source), max(1, every)):
        if len(rows) >= max_frames:
            break
        frame = source[index]
        if frame.T_W_S_gt is None:
            logger.warning("frame %d has no ground-truth pose; skipped", index)
            continue
        points, normals = frame_points(frame, cfg.submaps)
        try:
            results = two_paths(
                points,
                normals,
                np.asarray(frame.T_W_S_gt, dtype=np.float64),
                cfg.mapping,
                model,
                variants=variants,
                num_samples=num_samples,
            )
        except ValueError as exc:
            logger.warning("frame %d skipped: %s", index, exc)
            continue
        rows.append({"frame": index, "num_points": len(points), "variants": results})
        logger.info(
            "frame %d: %s",
            index,
            ", ".join(f"{k} acc {100 * v['accuracy_m']:.2f} cm" for k, v in results.items()),
        )
    return rows


def summarize(rows: list[dict[str, Any]], variants: Sequence[str]) -> dict[str, dict[str, float]]:
    """Mean and median over frames of accuracy, completion (m) and completion ratio per variant."""
    summary: dict[str, dict[str, float]] = {}
    for name in variants:
        values = {
            key: np.array([row["variants"][name][key] for row in rows], dtype=np.float64)
            for key in ("accuracy_m", "completion_m", "completion_ratio", "move_s")
        }
        summary[name] = {"frames": len(rows)}
        for key, array in values.items():
            summary[name][f"{key}_mean"] = float(np.mean(array)) if len(array) else float("nan")
            summary[name][f"{key}_median"] = float(np.median(array)) if len(array) else float("nan")
    return summary


def summary_markdown(summary: dict[str, dict[str, float]], command: str) -> str:
    """A Markdown table of :func:`summarize`."""
    lines = [
        "| variant | frames | accuracy mean / median [cm] | completion mean / median [cm] "
        "| completion ratio (< 5 cm) mean | move time mean [s] |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name, s in summary.items():
        lines.append(
            f"| {name} | {s['frames']} | {100 * s['accuracy_m_mean']:.2f} / "
            f"{100 * s['accuracy_m_median']:.2f} | {100 * s['completion_m_mean']:.2f} / "
            f"{100 * s['completion_m_median']:.2f} | {100 * s['completion_ratio_mean']:.1f} % | "
            f"{s['move_s_mean']:.2f} |"
        )
    return f"Command: `{command}`\n\n" + "\n".join(lines) + "\n"


def write_outputs(
    out_dir: Path, rows: list[dict[str, Any]], variants: Sequence[str], command: str
) -> dict[str, Path]:
    """``results.json``, ``summary.md`` and ``transform_distributions.png`` in ``out_dir``."""
    from common.atomic_io import write_text_atomic
    from slam.evaluation import plots
    from slam.run_folder.outputs import json_safe

    out_dir = Path(out_dir)
    summary = summarize(rows, variants)
    results_path = out_dir / "results.json"
    payload = {"command": command, "frames": rows, "summary": summary}
    write_text_atomic(results_path, json.dumps(json_safe(payload), indent=2) + "\n")
    summary_path = out_dir / "summary.md"
    write_text_atomic(summary_path, summary_markdown(summary, command))
    groups = {
        label: {name: [row["variants"][name][key] for row in rows] for name in variants}
        for label, key in (
            ("accuracy: moved -> re-encoded", "accuracy_m"),
            ("completion: re-encoded -> moved", "completion_m"),
        )
    }
    title = f"Encode-transform (moved map) vs transform-encode over {len(rows)} frames"
    figure = plots.save_png(
        plots.distributions_figure(groups, title=title), out_dir / "transform_distributions.png"
    )
    return {"results": results_path, "summary": summary_path, "plot": figure}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m slam.eval transform",
        description="Transform a neural map vs re-encode the transformed points, per frame.",
    )
    parser.add_argument("--dataset", default="demo", help="dataset name of python -m slam.run")
    parser.add_argument("--sequence", help="sequence name (real datasets)")
    parser.add_argument("--root", type=Path, help="dataset root folder")
    parser.add_argument("--config", type=Path, help="YAML config (default: configs/<dataset>.yaml)")
    parser.add_argument("--frames", help="frame range A:B[:STEP] of the source")
    parser.add_argument("--every", type=int, default=20, help="use every n-th frame (default 20)")
    parser.add_argument("--max-frames", type=int, default=12, help="at most this many frames")
    parser.add_argument(
        "--variants",
        default=",".join(DEFAULT_VARIANTS),
        help=f"comma-separated transform variants of {sorted(VARIANTS)}",
    )
    parser.add_argument("--samples", type=int, default=50_000, help="surface samples per mesh")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="config override"
    )
    parser.add_argument("--out", type=Path, help="output folder (default outputs/transform-...)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], help="torch device")
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m slam.eval transform``; returns the exit status."""
    from frontends.errors import DatasetError
    from slam.assembly.builders import build_source
    from slam.assembly.config import (
        ConfigError,
        UsageError,
        default_config_path,
        load_run_config,
        set_nested,
        set_overrides,
    )
    from slam.assembly.datasets import DATASETS
    from slam.assembly.threads import apply_thread_budget

    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]

    def config():
        entry = DATASETS.get(args.dataset)
        if entry is None or entry.path_argument:
            names = ", ".join(n for n, e in DATASETS.items() if not e.path_argument)
            raise UsageError(f"--dataset {args.dataset}: choose one of {names}")
        overrides = set_overrides(["source.depth.stride=1", *args.set])
        set_nested(overrides, "source.dataset", entry.source)
        for key, value in (
            ("source.sequence", args.sequence),
            ("source.root", None if args.root is None else str(args.root)),
            ("source.frames", args.frames),
            ("mapping.device", args.device),
        ):
            if value is not None:
                set_nested(overrides, key, value)
        set_nested(overrides, "viz.mode", "none")
        return load_run_config(args.config or default_config_path(entry.config), overrides)

    command = "python -m slam.eval transform " + " ".join(argv)
    try:
        cfg = config()
        apply_thread_budget(cfg)
        source = build_source(cfg)
        rows = run_transform_experiment(
            source,
            cfg,
            every=args.every,
            max_frames=args.max_frames,
            variants=variants,
            num_samples=args.samples,
        )
        if not rows:
            raise ValueError("no frame could be evaluated (no ground-truth poses?)")
        stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
        name = "-".join(p for p in ("transform", args.dataset, args.sequence) if p)
        out_dir = args.out or cfg.output.root / f"{name}-{stamp}"
        files = write_outputs(out_dir, rows, variants, command)
    except (UsageError, ConfigError, DatasetError, FileNotFoundError, ValueError) as exc:
        if args.debug:
            raise
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 1
    print(files["summary"].read_text())
    for label, path in files.items():
        print(f"{label}: {path}")
    return 0
