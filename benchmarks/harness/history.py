"""The report's "History" section: one link to the archive's index, nothing inlined.

``benchmarks/archive/`` keeps what an invocation of ``run_all`` does not measure again: the
full-length runs (longer than a quick invocation allows), before/after tables of changes, and the
report as it stood before the one-command harness. Each file states its own command, revision,
date and machine; ``benchmarks/archive/README.md`` lists every one with what it measured
(tests/test_benchmarks.py keeps that index in step with the files).
"""

from __future__ import annotations

import re
from pathlib import Path

from benchmarks.harness.paths import REPO

ARCHIVE_DIR = REPO / "benchmarks" / "archive"
ARCHIVE_INDEX = ARCHIVE_DIR / "README.md"


def archived_files(archive_dir: Path = ARCHIVE_DIR) -> list[str]:
    """The report files in ``archive_dir`` (``.md`` but the READMEs), relative to it."""
    return sorted(
        str(path.relative_to(archive_dir))
        for path in archive_dir.rglob("*.md")
        if path.name != "README.md"
    )


def indexed_files(index: Path = ARCHIVE_INDEX) -> list[str]:
    """The files the archive's index links from its list items, in its order."""
    return re.findall(r"^- \[[^\]]+\]\(([^)]+)\)", index.read_text(), flags=re.MULTILINE)


def history_lines(link_prefix: str = "benchmarks/archive") -> list[str]:
    """The "History" section: where the earlier and full-length runs are."""
    return [
        "## History",
        "",
        "Earlier and full-length runs are not part of this invocation. They are kept in "
        f"`{link_prefix}/`, each file naming its own command, revision, date and machine; "
        f"[{link_prefix}/README.md]({link_prefix}/README.md) lists them with what each measured.",
        "",
    ]
