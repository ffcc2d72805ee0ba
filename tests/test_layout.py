"""The layout shows the architecture: who may import whom, and files stay small.

Rules (README, "How the code is organised"): ``frontends/`` and ``mapping/`` import neither each
other nor ``slam/``; the algorithm (``slam/algorithm``) imports no application or evaluation
module, no viewer, plotting or argument parsing; evaluation never imports the run CLI.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
MAX_LINES = 500
# Files allowed past MAX_LINES (none today; the issue allowed the scene generators).
LONG_FILES_ALLOWED: set[str] = set()


def _imports(path: Path) -> set[str]:
    """Every module a file imports, at any depth (function-level imports included)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def _sources(folder: str) -> list[Path]:
    return sorted((REPO_ROOT / folder).rglob("*.py"))


def _violations(folder: str, forbidden: tuple[str, ...]) -> list[str]:
    found = []
    for path in _sources(folder):
        for name in _imports(path):
            if any(name == f or name.startswith(f + ".") for f in forbidden):
                found.append(f"{path.relative_to(REPO_ROOT)} imports {name}")
    return found


@pytest.mark.parametrize(
    ("folder", "forbidden"),
    [
        ("frontends", ("slam", "mapping")),
        ("mapping", ("slam", "frontends")),
        ("common", ("slam", "mapping", "frontends")),
        (
            "slam/algorithm",
            ("slam.app", "slam.evaluation", "rerun", "matplotlib", "argparse"),
        ),
        ("slam/evaluation", ("slam.app.cli", "slam.app.runner", "slam.run")),
    ],
)
def test_import_rules(folder: str, forbidden: tuple[str, ...]) -> None:
    assert _sources(folder), f"{folder} holds no Python file"
    assert _violations(folder, forbidden) == []


def test_the_checker_sees_function_level_imports(tmp_path: Path) -> None:
    module = tmp_path / "m.py"
    module.write_text("def f():\n    import rerun\n    from slam.app.cli import main\n")
    assert _imports(module) == {"rerun", "slam.app.cli"}


def test_no_source_file_is_over_500_lines() -> None:
    long_files = []
    for folder in ("frontends", "mapping", "common", "slam", "benchmarks", "tests", "docs"):
        for path in _sources(folder):
            relative = str(path.relative_to(REPO_ROOT))
            lines = len(path.read_text().splitlines())
            if lines > MAX_LINES and relative not in LONG_FILES_ALLOWED:
                long_files.append(f"{relative}: {lines} lines")
    assert long_files == []
