"""Repeated timings: every timing a benchmark reports is the median of ``REPEATS`` runs, shown
with its range as ``median (min-max)``.

:func:`timed` repeats a call; :func:`repeat_runs` repeats a measurement that returns a dict and
folds its timing fields into :class:`Timing` values (the other fields are the first run's: the
runs are deterministic). A :class:`Timing` is a float (its median) whose format spec prints the
range too (``f"{t:.1f}"`` gives ``12.3 (11.9-13.0)``); in JSON it is its median, the samples kept
beside it under ``"timings"`` (:func:`restore` rebuilds them).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Iterable
from typing import Any

REPEATS = 3
"""How many times every timing is measured."""


class Timing(float):
    """The median of repeated timings, formatted with their range (see the module docstring)."""

    samples: tuple[float, ...]

    def __new__(cls, samples: Iterable[float]) -> Timing:
        values = tuple(float(v) for v in samples)
        if not values:
            raise ValueError("a timing needs at least one sample")
        timing = super().__new__(cls, statistics.median(values))
        timing.samples = values
        return timing

    def scaled(self, factor: float) -> Timing:
        """The same timing in other units (e.g. ms) or per operation."""
        return Timing(factor * v for v in self.samples)

    def __format__(self, spec: str) -> str:
        median = float.__format__(float(self), spec)
        if len(self.samples) < 2:
            return median
        low, high = (float.__format__(v, spec) for v in (min(self.samples), max(self.samples)))
        return f"{median} ({low}-{high})"


def timed(fn: Callable[[], Any], repeats: int = REPEATS, warmup: bool = False) -> dict[str, Any]:
    """Wall and CPU seconds (this process, all threads) of ``fn()`` over ``repeats`` calls
    (after one untimed call with ``warmup``): ``{"wall_s": Timing, "cpu_s": Timing, "result":
    the last call's result}``."""
    if warmup:
        fn()
    walls, cpus, result = [], [], None
    for _ in range(max(1, repeats)):
        wall, cpu = time.perf_counter(), time.process_time()
        result = fn()
        walls.append(time.perf_counter() - wall)
        cpus.append(time.process_time() - cpu)
    return {"wall_s": Timing(walls), "cpu_s": Timing(cpus), "result": result}


def _fold(values: list[Any]) -> Any:
    """A :class:`Timing` of the numbers, a dict of them key by key; a run without the field
    (None) is left out."""
    present = [v for v in values if v is not None]
    if not present:
        return None
    if isinstance(present[0], dict):
        return {key: _fold([v.get(key) for v in present]) for key in present[0]}
    return Timing(present)


def repeat_runs(
    run: Callable[[], dict[str, Any]], timing_keys: Iterable[str], repeats: int = REPEATS
) -> dict[str, Any]:
    """``run()`` ``repeats`` times; the first result with every field of ``timing_keys`` (a
    number, or a dict of numbers) folded into :class:`Timing` values over the runs. A result
    without a timing (a skipped run) is returned as it is, after one run."""
    results = [run()]
    keys = [key for key in timing_keys if results[0].get(key) is not None]
    if not keys:
        return results[0]
    results += [run() for _ in range(max(1, repeats) - 1)]
    first = dict(results[0])
    for key in keys:
        first[key] = _fold([result.get(key) for result in results])
    first["repeats"] = len(results)
    first["timings"] = {key: _samples(first[key]) for key in keys}
    return first


def _samples(value: Any) -> Any:
    if isinstance(value, dict):
        return {key: _samples(v) for key, v in value.items()}
    return None if value is None else list(value.samples)


def _rebuild(samples: Any) -> Any:
    if isinstance(samples, dict):
        return {key: _rebuild(v) for key, v in samples.items()}
    return None if samples is None else Timing(samples)


def restore(result: dict[str, Any]) -> dict[str, Any]:
    """A :func:`repeat_runs` result read back from JSON, with its :class:`Timing` values."""
    out = dict(result)
    for key, samples in result.get("timings", {}).items():
        out[key] = _rebuild(samples)
    return out


def restore_all(saved: Any) -> Any:
    """A whole results file read back from JSON: every :func:`repeat_runs` result in it (at any
    depth) with its :class:`Timing` values, for a ``--report-only`` rewrite."""
    if isinstance(saved, list):
        return [restore_all(v) for v in saved]
    if not isinstance(saved, dict):
        return saved
    out = {key: restore_all(v) for key, v in saved.items()}
    return restore(out) if "timings" in saved else out


def repeats_line(deterministic: str = "", repeats: int = REPEATS) -> str:
    """The line every section states about its timings."""
    line = (
        f"- Timings: median of {repeats} runs (min-max); other jobs on the shared machine "
        "inflate the max."
    )
    return f"{line} {deterministic}" if deterministic else line
