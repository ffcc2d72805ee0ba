"""What every benchmark's command line shares: its parser, the command it states, its log."""

from __future__ import annotations

import argparse
import logging
import shlex
import sys
from pathlib import Path


def bench_parser(doc: str, quick: str, *, before: bool = False, out: Path | None = None):
    """A parser described by ``doc``'s first line, with ``--quick`` (help ``quick``), and
    ``--before REV`` and ``--out FILE`` (default ``out``) where asked."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=quick)
    if before:
        parser.add_argument("--before", metavar="REV", help="also measure revision REV")
    if out is not None:
        parser.add_argument("--out", type=Path, default=out, help="Markdown section to write")
    return parser


def command_line(module: str, argv: list[str] | None) -> str:
    """The command a section states: ``python -m benchmarks.<module>`` and its arguments."""
    shown = sys.argv[1:] if argv is None else argv
    return shlex.join(["python", "-m", f"benchmarks.{module}", *shown])


def start_logging(fmt: str = "%(message)s") -> None:
    """INFO messages of every logger to stderr, in ``fmt``."""
    logging.basicConfig(level=logging.INFO, format=fmt)
