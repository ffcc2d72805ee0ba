"""The fleet's progress display: runs done, running and failed, and the frame rate of each run
going on, read from the ``run_status.json`` that every run rewrites as it goes.

A tqdm bar on a terminal; elsewhere (a log file, a batch job) one line per run that ends.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path

from slam.run_folder.outputs import RUN_STATUS_FILE, read_run_status


@dataclass
class _Watch:
    """A running run's first status seen (frames done then, and when it was written)."""

    frames: int
    seen_at: float


@dataclass
class FleetProgress:
    """Tracks the runs of a fleet; ``bar`` is shown only when ``live``."""

    total: int
    live: bool
    done: int = 0
    failed: int = 0
    running: dict[str, Path] = field(default_factory=dict)
    _watch: dict[str, _Watch] = field(default_factory=dict)
    _bar: object = None

    def __post_init__(self) -> None:
        if self.live:
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, unit="run", desc="runs", dynamic_ncols=True)

    def start(self, name: str, folder: Path) -> None:
        self.running[name] = folder

    def reuse(self, name: str) -> None:
        self.done += 1
        self._advance()
        self.say(f"{name}: finished earlier, reused")

    def end(self, name: str, ok: bool, line: str) -> None:
        """A run ended (``line``: what to tell the user about it)."""
        self.running.pop(name, None)
        self._watch.pop(name, None)
        if ok:
            self.done += 1
        else:
            self.failed += 1
        self._advance()
        self.say(line)

    def say(self, line: str) -> None:
        if self._bar is not None:
            self._bar.write(line, file=sys.stderr)
        else:
            print(line, file=sys.stderr, flush=True)

    def rates(self) -> dict[str, str]:
        """``name -> "frames/total rate fps"`` of every run going on: the frames done since its
        status was first seen, over the time from then to the status's last update."""
        out = {}
        for name, folder in self.running.items():
            status = read_run_status(folder)
            if status is None or status.get("state") != "running":
                continue
            frames = int(status.get("frames_done") or 0)
            try:
                updated_at = (folder / RUN_STATUS_FILE).stat().st_mtime
            except OSError:
                continue
            watch = self._watch.setdefault(name, _Watch(frames, updated_at))
            elapsed = updated_at - watch.seen_at
            rate = (frames - watch.frames) / elapsed if elapsed > 0 else 0.0
            out[name] = f"{frames}/{status.get('frames_total')} {rate:.1f} fps"
        return out

    def refresh(self) -> None:
        if self._bar is None:
            return
        rates = self.rates()
        text = f"done {self.done}, running {len(self.running)}, failed {self.failed}"
        if rates:
            text += " | " + ", ".join(f"{name} {rate}" for name, rate in rates.items())
        self._bar.set_postfix_str(text, refresh=True)

    def _advance(self) -> None:
        if self._bar is not None:
            self._bar.update(1)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
