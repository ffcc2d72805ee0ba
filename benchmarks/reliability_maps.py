"""Reliability cases of map files from elsewhere (``bench_reliability.py --only maps``): crafted
``map.npz`` files given to ``slam.merge``, ``slam.run --map`` and ``slam.eval``, a run merged
with itself, ``--map`` of another sensor, merges stopped by SIGTERM or racing for one ``--out``,
and ``slam.eval`` of a merged run. Each cell says what the user saw and what was left behind."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

from benchmarks.harness.crafted_maps import CRAFTED, header_edit
from benchmarks.harness.reliability import PY, Case, Outcome, outcome, run

_MERGEABLE: dict[Path, Path] = {}


def _left(folder: Path, keep: set[str]) -> str:
    extra = sorted(p.name for p in folder.iterdir() if p.name not in keep)
    return f"leftovers: {', '.join(extra) if extra else 'none'}"


def _crafted(base: Path, work: Path, craft) -> Path:
    folder = work / "crafted"
    folder.mkdir()
    craft(base / "map.npz", folder / "map.npz")
    return folder


def _merge_case(name: str):
    def case(code: Path, work: Path, base: Path) -> Outcome:
        folder = _crafted(base, work, CRAFTED[name])
        out = work / "merged"
        result = run(code, [PY, "-m", "slam.merge", str(base), str(folder), "--no-viz", "--out",
                            str(out)], timeout=300)  # fmt: skip
        return outcome(result, _left(work, {"crafted"}))

    return case


def _lie_case(**config):
    def case(code: Path, work: Path, base: Path) -> Outcome:
        folder = work / "run"
        shutil.copytree(base, folder)
        header_edit(**config)(base / "map.npz", folder / "map.npz")
        result = run(code, [PY, "-m", "slam.eval", str(folder), "--no-plots"], timeout=300)
        return outcome(result)

    return case


def _second_run(code: Path, work: Path) -> Path:
    """A run of frames 5:15 (it shares places with the base run's 0:10), made once per tree."""
    if code not in _MERGEABLE:
        out = work / "second"
        result = run(code, [PY, "-m", "slam.run", "demo", "--no-progress", "--no-viz",
                            "--frames", "5:15", "--set", "output.mesh_samples=0", "--out",
                            str(out)])  # fmt: skip
        if result.returncode != 0:
            raise RuntimeError(f"second run failed: {result.stderr[-300:]}")
        _MERGEABLE[code] = out
    return _MERGEABLE[code]


def case_self_merge(code: Path, work: Path, base: Path) -> Outcome:
    out = work / "self"
    result = run(code, [PY, "-m", "slam.merge", str(base), str(base), "--no-viz", "--out",
                        str(out)])  # fmt: skip
    rows = len((out / "poses_slam.kitti.txt").read_text().splitlines()) if out.exists() else 0
    return outcome(result, f"{rows} poses written for 10 frames")


def case_map_other_sensor(code: Path, work: Path, base: Path) -> Outcome:
    start = time.perf_counter()
    result = run(code, [PY, "-m", "slam.run", "generated-lidar", "--frames", "0:30",
                        "--no-viz", "--no-progress", "--map", str(base), "--out",
                        str(work / "out")])  # fmt: skip
    return outcome(result, f"{time.perf_counter() - start:.0f} s; {_left(work, set())}")


def _merge_process(code: Path, base: Path, second: Path, out: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(code)}
    return subprocess.Popen(
        [PY, "-m", "slam.merge", str(base), str(second), "--no-viz", "--out", str(out)],
        cwd=code, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


def case_merge_sigterm(code: Path, work: Path, base: Path) -> Outcome:
    second = _second_run(code, work.parent)
    out = work / "merged"
    process = _merge_process(code, base, second, out)
    time.sleep(8.0)  # past the imports, into loading and verification
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=300)
    lines = [line for line in err.splitlines() if line.strip()]
    return Outcome(process.returncode, lines[-1] if lines else "(no output)", _left(work, set()))


def case_concurrent_merges(code: Path, work: Path, base: Path) -> Outcome:
    second = _second_run(code, work.parent)
    out = work / "merged"
    first, other = (_merge_process(code, base, second, out) for _ in range(2))
    errors = [p.communicate(timeout=600)[1] for p in (first, other)]
    codes = f"exit codes {first.returncode} and {other.returncode}"
    refused = [e.strip().splitlines()[-1] for e in errors if "error:" in e]
    message = refused[0] if refused else "(both succeeded)"
    probe = f"{codes}; {_left(work, {'merged'})}"
    return Outcome(other.returncode or first.returncode, message, probe)


def case_eval_merged(code: Path, work: Path, base: Path) -> Outcome:
    second = _second_run(code, work.parent)
    out = work / "merged"
    merged = run(code, [PY, "-m", "slam.merge", str(base), str(second), "--no-viz", "--out",
                        str(out)])  # fmt: skip
    if merged.returncode != 0:
        return outcome(merged, "the merge itself failed")
    return outcome(run(code, [PY, "-m", "slam.eval", str(out), "--no-plots"]))


MAP_CASES = [
    *(Case("M1", name, "slam.merge BASE CRAFTED", _merge_case(name), group="maps")
      for name in CRAFTED),
    Case("M2", "header weights_path /etc/passwd", "slam.eval RUN", _lie_case(
        weights_path="/etc/passwd"), group="maps"),
    Case("M2", "header device cuda (no GPU)", "slam.eval RUN", _lie_case(device="cuda"),
         group="maps"),
    Case("M6", "run merged with itself", "slam.merge BASE BASE", case_self_merge, group="maps"),
    Case("M7", "--map of another sensor", "slam.run generated-lidar --frames 0:30 --map BASE",
         case_map_other_sensor, group="maps"),
    Case("M4", "SIGTERM 8 s into a merge", "kill -TERM during slam.merge BASE SECOND",
         case_merge_sigterm, quick=False, group="maps"),
    Case("M5", "two merges into one --out at once", "slam.merge BASE SECOND --out M (twice)",
         case_concurrent_merges, quick=False, group="maps"),
    Case("M8", "slam.eval of a merged run", "slam.eval MERGED", case_eval_merged, quick=False,
         group="maps"),
]  # fmt: skip
