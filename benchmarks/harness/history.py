"""The report's "History" section: one link to the archive's index, nothing inlined.

``benchmarks/archive/`` keeps what an invocation of ``run_all`` does not measure again (full-length
runs, before/after tables, the report before the one-command harness), each file naming its own
command, revision, date and machine; ``benchmarks/archive/README.md`` lists them
(tests/test_benchmarks.py keeps that index in step with the files).
"""

from __future__ import annotations


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
