"""A benchmark's scenarios, each in a work folder of its own, and its two result files."""

from __future__ import annotations

import json
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from benchmarks.harness.paths import RESULTS_DIR
from common.atomic_io import write_text_atomic


def run_scenarios(
    names: Iterable[str],
    run: Callable[[str, Path], dict[str, Any]],
    prefix: str,
    work_root: Path | None,
) -> dict[str, dict[str, Any]]:
    """``run(name, work)`` of each scenario, in a new folder ``work`` under ``work_root`` (the
    system's temporary folder without one; created when missing); a scenario whose data is
    absent (its ``FileNotFoundError``) is recorded as ``{"skipped": reason}``."""
    results = {}
    if work_root is not None:
        work_root.mkdir(parents=True, exist_ok=True)
    for name in names:
        work = Path(tempfile.mkdtemp(prefix=f"{prefix}-{name}-", dir=work_root))
        try:
            results[name] = run(name, work)
        except FileNotFoundError as exc:
            results[name] = {"skipped": str(exc)}
    return results


def scenario_arguments(parser, choices: Iterable[str], default: str) -> None:
    """``--scenario NAME...`` (help: the ``default`` choice) and ``--work DIR``."""
    parser.add_argument("--scenario", nargs="+", choices=choices, help=f"default: {default}")
    parser.add_argument("--work", type=Path, help="work folder (default: a temporary one)")


def write_results(stem: str, results: dict[str, Any], markdown: str) -> None:
    """``benchmarks/results/<stem>.json`` (the numbers) and ``<stem>.md`` (the section)."""
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    write_text_atomic(RESULTS_DIR / f"{stem}.json", json.dumps(results, indent=2) + "\n")
    write_text_atomic(RESULTS_DIR / f"{stem}.md", markdown)


def table(header: str, rows: Iterable[Iterable[Any]], align: str = "") -> list[str]:
    """A Markdown table: ``header`` (its cells split at `` | ``), its rule (``align``: one letter
    per column, ``r`` right-aligned, else left) and one line per row of cells."""
    names = header.split(" | ")
    rule = "|".join("---:" if align[i : i + 1] == "r" else "---" for i in range(len(names)))
    return [f"| {header} |", f"|{rule}|", *("| " + " | ".join(map(str, r)) + " |" for r in rows)]


def cm(value_m: float | None, digits: int = 1) -> str:
    """Metres as centimetres with ``digits`` decimals; ``-`` for a missing value."""
    return "-" if value_m is None else f"{100 * value_m:.{digits}f}"
