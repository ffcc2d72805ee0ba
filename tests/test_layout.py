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
            (
                "slam.app",
                "slam.assembly",
                "slam.evaluation",
                "slam.run_folder",
                "rerun",
                "matplotlib",
                "argparse",
            ),
        ),
        ("slam/assembly", ("slam.app", "slam.evaluation", "slam.run_folder", "rerun")),
        ("slam/run_folder", ("slam.app", "slam.evaluation", "rerun")),
        ("slam/evaluation", ("slam.app", "slam.run", "slam.merge", "rerun")),
    ],
)
def test_import_rules(folder: str, forbidden: tuple[str, ...]) -> None:
    assert _sources(folder), f"{folder} holds no Python file"
    assert _violations(folder, forbidden) == []


RAY_MODULES = {"slam/app/fleet_ray.py"}
"""The only modules that may import ``ray`` (an optional extra): the fleet's."""


def test_only_the_fleet_imports_ray() -> None:
    found = []
    for folder in ("frontends", "mapping", "common", "slam"):
        for path in _sources(folder):
            relative = str(path.relative_to(REPO_ROOT))
            if relative not in RAY_MODULES and any(
                name == "ray" or name.startswith("ray.") for name in _imports(path)
            ):
                found.append(relative)
    assert found == []
    for relative in RAY_MODULES:
        assert "ray" in _imports(REPO_ROOT / relative), relative


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO_ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _import_graph(package: str) -> dict[str, set[str]]:
    """Module -> the package's modules it imports, at any depth, relative imports resolved.

    ``from a.b import c`` counts as an import of the module ``a.b.c`` where there is one, else of
    ``a.b``."""
    modules = {_module_name(p): p for p in _sources(package)}

    def known(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for module, path in modules.items():
        base_package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = base_package.split(".")
                    base = ".".join([*parts[: len(parts) - node.level + 1], *filter(None, [base])])
                submodules = [f"{base}.{alias.name}" for alias in node.names]
                names = [n if n in modules else base for n in submodules]
            else:
                continue
            targets.update(t for n in names if (t := known(n)) and t != module)
        graph[module] = targets
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle through each strongly connected component of more than one node (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph.get(node, ())):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def _collapsed(graph: dict[str, set[str]], depth: int) -> dict[str, set[str]]:
    """The graph between sub-packages: every module ``depth`` or more levels down is merged
    into its package at that depth (``slam.algorithm.loops.lidar`` -> ``slam.algorithm.loops``);
    modules higher up stay nodes of their own."""

    def node(module: str) -> str:
        parts = module.split(".")
        return ".".join(parts[:depth]) if len(parts) > depth else module

    collapsed: dict[str, set[str]] = {}
    for module, targets in graph.items():
        source = node(module)
        collapsed.setdefault(source, set()).update(
            t for t in map(node, targets) if t != source and not t.startswith(source + ".")
        )
    return collapsed


@pytest.mark.parametrize("package", ["slam", "mapping", "frontends", "common"])
def test_no_import_cycle_between_modules_or_sub_packages(package: str) -> None:
    graph = _import_graph(package)
    assert _cycles(graph) == []
    assert _cycles(_collapsed(graph, depth=3)) == []
    assert _cycles(_collapsed(graph, depth=2)) == []


def test_the_cycle_checker_finds_a_cycle_through_a_function_level_import(tmp_path: Path) -> None:
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles(_collapsed({"p.q.x": {"p.q.y"}, "p.q.y": {"p.r"}, "p.r": {"p.q.x"}}, 2)) == [
        ["p.q", "p.r"]
    ]
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from . import sibling\n")
    assert "." not in _imports(module)


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


def _test_module_imports(path: Path) -> list[str]:
    """The test modules (``test_*``) that a file imports, in any spelling: ``tests.test_x``,
    ``test_x``, ``from tests import test_x`` or ``from . import test_x``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            modules = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            modules = [base] + [f"{base}.{alias.name}".lstrip(".") for alias in node.names]
        else:
            continue
        found += [m for m in modules if m.rsplit(".", 1)[-1].startswith("test_")]
    return found


def test_no_test_module_imports_another() -> None:
    """Shared fixtures live in tests/conftest.py and shared helpers in plain modules
    (tests/helpers.py, ...): a test file imported by another would run its tests twice and tie
    the two files' fixtures together."""
    found = [
        f"{path.relative_to(REPO_ROOT)} imports {name}"
        for path in _sources("tests")
        for name in _test_module_imports(path)
    ]
    assert found == []


def test_the_test_import_checker_sees_every_spelling(tmp_path: Path) -> None:
    spellings = (
        "from tests.test_plots import x",
        "import tests.test_plots",
        "from tests import test_plots",
        "from . import test_plots",
        "import test_plots",
        "from test_plots import x",
    )
    for line in spellings:
        (tmp_path / "a.py").write_text(f"def f():\n    {line}\n")
        assert _test_module_imports(tmp_path / "a.py"), line
    (tmp_path / "b.py").write_text("from tests.helpers import call_main\nimport pytest\n")
    assert _test_module_imports(tmp_path / "b.py") == []
