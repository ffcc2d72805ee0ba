"""Reliability cases, run as a user would, before and after the fixes.

    python benchmarks/bench_reliability.py [--quick] [--only general|maps|commands] [--before REV]
        [--out FILE]

Each case is a command on generated data in a temporary folder (bad input, environment errors,
signals, ``--serve``); the table records its exit code, the line that tells the user what
happened (the ``error:`` line, else the first warning, else the last line of a traceback), what a
probe saw (bound addresses, file modes, temporaries left) and the command's peak RSS.
``--before REV`` runs every case also against a checkout of REV; ``--quick`` leaves out the cases
that run the pipeline more than once. Groups (``--only``): ``general`` here, ``maps`` in
``benchmarks/reliability_maps.py``, ``commands`` in ``benchmarks/reliability_commands.py``; a
table per group counts one-line errors, tracebacks and cases that left files behind.
Writes ``benchmarks/results/reliability.md``.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import stat
import struct
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

from benchmarks.harness.checkout import checkout
from benchmarks.harness.cli import bench_parser
from benchmarks.harness.net import free_port, listening_addresses
from benchmarks.harness.paths import REPO, RESULTS_DIR
from benchmarks.harness.reliability import PY, Case, Outcome, message_of, outcome, run
from benchmarks.harness.results import table
from benchmarks.reliability_commands import COMMAND_CASES
from benchmarks.reliability_maps import MAP_CASES
from common.atomic_io import write_text_atomic

DEMO = ["demo", "--no-progress", "--set", "output.mesh_samples=1000"]


def slam_run(code: Path, *args: str) -> subprocess.CompletedProcess:
    return run(code, [PY, "-m", "slam.run", *args])


def slam_eval(code: Path, run_folder: Path) -> subprocess.CompletedProcess:
    return run(code, [PY, "-m", "slam.eval", str(run_folder), "--no-plots"])


def python_snippet(code: Path, snippet: str) -> subprocess.CompletedProcess:
    return run(code, [PY, "-c", "import logging; logging.basicConfig()\n" + snippet])


def demo_case(*args: str):
    """A case that is ``slam.run demo --no-viz ARGS``, reported as it is."""
    return lambda code, work, base: outcome(slam_run(code, *DEMO, "--no-viz", *args))


def written(path: Path) -> str:
    return f"{path.name} {'written' if path.exists() else 'absent'}"


def temporaries(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob(".*") if p.is_file()) if folder.exists() else []


# -- generated inputs --------------------------------------------------------------------------


def write_tum(folder: Path, n_rgb: int, n_depth: int, size=(48, 64), intrinsics=True) -> None:
    import cv2

    for sub in ("rgb", "depth"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    rgb_lines, depth_lines = [], []
    for i in range(max(n_rgb, n_depth)):
        t = 100.0 + i / 30
        if i < n_rgb:
            cv2.imwrite(str(folder / "rgb" / f"{t:.6f}.png"), np.full((*size, 3), 128, np.uint8))
            rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        if i < n_depth:
            depth = np.full(size, 5000, np.uint16)
            cv2.imwrite(str(folder / "depth" / f"{t:.6f}.png"), depth)
            depth_lines.append(f"{t:.6f} depth/{t:.6f}.png")
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if intrinsics:
        h, w = size
        (folder / "intrinsics.txt").write_text(f"50 50 {w / 2} {h / 2} {w} {h} 5000\n")


def flip_member(path: Path, out: Path, member: str = "latent_coeffs.npy") -> None:
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as z:
        info = z.getinfo(member)
    offset = info.header_offset
    name_len, extra_len = struct.unpack("<HH", data[offset + 26 : offset + 30])
    start = offset + 30 + name_len + extra_len + 2  # the deflate block header: zlib.error
    for i in range(16):
        data[start + i] ^= 0xFF
    out.write_bytes(bytes(data))


def in_tmpfs(folder: Path, options: str, *args: str) -> Outcome:
    """``slam.run args`` with a tmpfs mounted (``options``) at ``folder``; root only."""
    folder.mkdir(parents=True, exist_ok=True)
    mount = ["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)]
    if os.geteuid() != 0 or subprocess.run(mount).returncode != 0:
        return Outcome(None, "skipped: needs root and tmpfs mounts")
    try:
        return outcome(slam_run(*args))
    finally:
        subprocess.run(["umount", str(folder)], capture_output=True)


# -- cases -------------------------------------------------------------------------------------


def case_serve(code: Path, work: Path, base: Path) -> Outcome:
    web, grpc = free_port(), free_port()
    args = [PY, "-m", "slam.run", *DEMO, "--frames", "0:3", "--serve", "--set",
            "viz.serve_linger_s=5", "--set", f"viz.serve_web_port={web}", "--set",
            f"viz.serve_grpc_port={grpc}", "--out", str(work / "serve")]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(code)}
    process = subprocess.Popen(
        args, cwd=code, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    seen_web, seen_grpc = set(), set()
    deadline = time.monotonic() + 300
    while process.poll() is None and time.monotonic() < deadline:
        seen_web |= listening_addresses(web)
        seen_grpc |= listening_addresses(grpc)
        time.sleep(0.1)
    _, err = process.communicate(timeout=60)
    lines = [line for line in err.splitlines() if line.startswith("viewer:")]
    probe = f"web {sorted(seen_web) or '-'}, data {sorted(seen_grpc) or '-'}"
    return Outcome(process.returncode, lines[0] if lines else message_of(err), probe)


def case_corrupt_map(code: Path, work: Path, base: Path) -> Outcome:
    bad = work / "bad.npz"
    flip_member(base / "map.npz", bad)
    snippet = f"from mapping.map_io import load_map\nload_map({str(bad)!r})"
    return outcome(run(code, [PY, "-c", snippet]))


def case_corrupt_map_eval(code: Path, work: Path, base: Path) -> Outcome:
    copy = work / "run"
    shutil.copytree(base, copy)
    flip_member(base / "map.npz", copy / "map.npz")
    return outcome(slam_eval(code, copy))


def case_truncated_ply(code: Path, work: Path, base: Path) -> Outcome:
    scans = work / "scans"
    scans.mkdir()
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 1000\nproperty float x\n"
    header += "property float y\nproperty float z\nend_header\n"
    for i in range(3):
        (scans / f"{i:06d}.ply").write_bytes(header.encode() + b"\0" * 30)
    out = work / "run"
    result = slam_run(code, "lidar", str(scans), "--dataloader", "generic", "--no-viz",
                      "--no-progress", "--out", str(out))  # fmt: skip
    return outcome(result, written(out / "metrics.json"))


def case_disk_full(code: Path, work: Path, base: Path) -> Outcome:
    full = work / "full"
    return in_tmpfs(
        full,
        "size=160k",
        code,
        *DEMO,
        "--frames",
        "0:6",
        "--rrd",
        str(full / "o/recording.rrd"),
        "--out",
        str(full / "o"),
    )


def case_read_only_out(code: Path, work: Path, base: Path) -> Outcome:
    return in_tmpfs(work / "ro", "size=1m,ro", code, *DEMO, "--no-viz", "--out", str(work / "ro"))


def case_root_is_file(code: Path, work: Path, base: Path) -> Outcome:
    (work / "afile").write_text("")
    return outcome(slam_run(code, *DEMO, "--no-viz", "--set", f"output.root={work / 'afile'}"))


def case_bad_weights(code: Path, work: Path, base: Path) -> Outcome:
    import pickle

    weights = work / "foreign.pt"
    with weights.open("wb") as f:
        pickle.dump({"format": "neural-remap-slam/prior", "obj": Path("x")}, f)
    out = work / "run"
    result = slam_run(code, *DEMO, "--frames", "0:3", "--no-viz", "--set",
                      f"mapping.weights_path={weights}", "--out", str(out))  # fmt: skip
    hint = "offers weights_only=False" if "weights_only=False" in result.stderr else ""
    left = "folder left" if out.exists() and any(out.iterdir()) else "no folder left"
    return outcome(result, ", ".join(p for p in (hint, left) if p))


def case_eval_interrupted(code: Path, work: Path, base: Path) -> Outcome:
    copy = work / "run"
    shutil.copytree(base, copy)
    for name in ("metrics.json", "map.npz", "mesh.ply"):
        (copy / name).unlink(missing_ok=True)
    status = {"state": "interrupted", "frames_done": 5, "frames_total": 10, "reason": "Ctrl-C"}
    (copy / "run_status.json").write_text(json.dumps(status))
    return outcome(slam_eval(code, copy), written(copy / "metrics.json"))


def case_sigterm(code: Path, work: Path, base: Path) -> Outcome:
    out = work / "run"
    args = [PY, "-m", "slam.run", *DEMO, "--frames", "0:40", "--set", "submaps.max_frames=5",
            "--rrd", str(out / "recording.rrd"), "--out", str(out)]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(code)}
    process = subprocess.Popen(
        args, cwd=code, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    deadline = time.monotonic() + 300
    while not (out / "poses_slam.tum.txt").exists() and time.monotonic() < deadline:
        if process.poll() is not None:
            break
        time.sleep(0.02)
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=120)
    import rerun_cli

    binary = Path(rerun_cli.__file__).parent / "rerun"
    verify = subprocess.run([str(binary), "rrd", "verify", str(out / "recording.rrd")],
                            capture_output=True, timeout=120)  # fmt: skip
    probe = f"rrd verify {'ok' if verify.returncode == 0 else 'fails'}; "
    probe += f"temporaries {temporaries(out) or 'none'}"
    return Outcome(process.returncode, message_of(err), probe)


def case_map_mode(code: Path, work: Path, base: Path) -> Outcome:
    modes = {p.name: oct(stat.S_IMODE(p.stat().st_mode)) for p in base.iterdir() if p.is_file()}
    odd = {k: v for k, v in modes.items() if v != "0o644"}
    return Outcome(0, f"map.npz {modes.get('map.npz')}", f"not 0644: {odd or 'none'}")


def _tum_snippet(root: Path, sequence: str) -> str:
    return (
        "from frontends.sources import make_source\n"
        f"s = make_source('tum', root={str(root)!r}, sequence={sequence!r})\n"
        "print(len(s), 'frames')"
    )


def case_count_mismatch(code: Path, work: Path, base: Path) -> Outcome:
    write_tum(work / "seq", 40, 25)
    return outcome(python_snippet(code, _tum_snippet(work, "seq")))


def case_containment(code: Path, work: Path, base: Path) -> Outcome:
    write_tum(work / "seq", 4, 4)
    lines = (work / "seq" / "rgb.txt").read_text().splitlines()
    lines[1] = lines[1].split()[0] + " /etc/passwd"
    (work / "seq" / "rgb.txt").write_text("\n".join(lines) + "\n")
    return outcome(python_snippet(code, _tum_snippet(work, "seq")))


def case_no_intrinsics(code: Path, work: Path, base: Path) -> Outcome:
    write_tum(work / "my_camera", 3, 3, size=(480, 640), intrinsics=False)
    return outcome(python_snippet(code, _tum_snippet(work, "my_camera")))


def case_zero_depth_scale(code: Path, work: Path, base: Path) -> Outcome:
    write_tum(work / "seq", 3, 3)
    (work / "seq" / "intrinsics.txt").write_text("50 50 32 24 64 48 0\n")
    snippet = _tum_snippet(work, "seq") + "\nprint(len(s[0].points), 'points')"
    return outcome(python_snippet(code, snippet))


def case_eval_bad_tum(code: Path, work: Path, base: Path) -> Outcome:
    copy = work / "run"
    shutil.copytree(base, copy)
    (copy / "poses_slam.tum.txt").write_text("1.0 garbage\n")
    return outcome(slam_eval(code, copy))


def case_fsync(code: Path, work: Path, base: Path) -> Outcome:
    snippet = (
        "import os\n"
        "try:\n    from common.atomic_io import write_text_atomic\n"
        "except ImportError:\n    from slam.app.atomic_io import write_text_atomic\n"
        "calls = []\nreal = os.fsync\n"
        "os.fsync = lambda fd: (calls.append(fd), real(fd))\n"
        f"write_text_atomic({str(work / 'x.txt')!r}, 'x')\n"
        "print(f'fsync calls: {len(calls)}')"
    )
    return outcome(python_snippet(code, snippet))


CASES = [
    Case("1", "--serve binds the web viewer", "slam.run demo --serve --set viz.serve_linger_s=5",
         case_serve, quick=False),
    Case("2", "corrupted map.npz (16 flipped bytes in a member)", "load_map(bad.npz)",
         case_corrupt_map),
    Case("2", "corrupted map.npz in slam.eval", "slam.eval RUN", case_corrupt_map_eval),
    Case("3", "generic folder of truncated PLY files",
         "slam.run lidar scans/ --dataloader generic", case_truncated_ply),
    Case("4", "disk full (160 kB tmpfs)", "slam.run demo --rrd FULL/o/recording.rrd --out FULL/o",
         case_disk_full, quick=False),
    Case("4", "read-only --out (ro tmpfs)", "slam.run demo --out RO", case_read_only_out),
    Case("4", "output.root is a file", "slam.run demo --set output.root=afile", case_root_is_file),
    Case("4", "foreign prior weights (pickled object)",
         "slam.run demo --set mapping.weights_path=foreign.pt", case_bad_weights),
    Case("4", "--out /proc/x", "slam.run demo --out /proc/x", demo_case("--out", "/proc/x")),
    Case("5", "slam.eval on an interrupted run", "slam.eval RUN (run_status: interrupted)",
         case_eval_interrupted),
    Case("6", "SIGTERM after the first submap", "kill -TERM during slam.run demo --rrd",
         case_sigterm, quick=False),
    Case("7", "file modes of a run folder", "stat RUN/*", case_map_mode),
    Case("8", "40 RGB vs 25 depth images", "make_source('tum', ...)", case_count_mismatch),
    Case("9", "rgb.txt entry /etc/passwd", "make_source('tum', ...)", case_containment),
    Case("10", "--set validation error", "slam.run demo --set submaps.max_frames=abc",
         demo_case("--set", "submaps.max_frames=abc")),
    Case("11", "--set source.frames=10:5", "slam.run demo --set source.frames=10:5",
         demo_case("--set", "source.frames=10:5")),
    Case("12", "RGB-D folder without intrinsics.txt", "make_source('tum', ..., 'my_camera')",
         case_no_intrinsics),
    Case("12", "depth_scale 0 in intrinsics.txt", "make_source('tum', ...)[0]",
         case_zero_depth_scale),
    Case("13", "slam.eval with a malformed poses_slam.tum.txt", "slam.eval RUN",
         case_eval_bad_tum),
    Case("14", "--frames -5:10", "slam.run demo --frames -5:10", demo_case("--frames", "-5:10")),
    Case("14", "atomic writes fsync", "write_text_atomic(x.txt)", case_fsync),
]  # fmt: skip
CASES += MAP_CASES + COMMAND_CASES


def base_run(code: Path, work: Path) -> Path:
    out = work / "base-run"
    result = slam_run(code, *DEMO, "--frames", "0:10", "--no-viz", "--out", str(out))
    if result.returncode != 0:
        raise SystemExit(f"base run failed at {code}: {message_of(result.stderr)}")
    return out


def run_cases(code: Path, cases: list[Case], work: Path) -> list[Outcome]:
    base = base_run(code, work)
    outcomes = []
    for i, case in enumerate(cases):
        folder = work / f"case{i:02d}"
        folder.mkdir()
        try:
            outcomes.append(case.run(code, folder, base))
        except Exception as exc:  # a case that cannot run is reported, not fatal
            outcomes.append(Outcome(None, f"case failed: {type(exc).__name__}: {exc}"))
        print(f"  {case.number:>3} {case.title}: {outcomes[-1]}", file=sys.stderr)
    return outcomes


CELL_MAX_CHARS = 200
"""A table cell's message is cut here (the whole line is in the JSON results)."""
_WORK_PATH = re.compile(r"/\S*/bench-reliability-[^/\s]+/work-(?:before|after)/case\d+/")
"""The temporary case folder in a message: the same in every row, so it is left out."""


def cell(o: Outcome | None) -> str:
    if o is None:
        return "-"
    message = _WORK_PATH.sub("", o.message)
    if len(message) > CELL_MAX_CHARS:
        message = message[: CELL_MAX_CHARS - 3] + "..."
    text = f"**{o.status}** {message}" + (f" [{o.probe}]" if o.probe else "")
    if o.peak_rss_mb is not None:
        text += f" ({o.peak_rss_mb:.0f} MB)"
    return text.replace("|", "\\|").replace("\n", " ")


def class_summary(outcomes: list[Outcome | None]) -> str:
    """Cases tried, one-line errors, tracebacks, cases that left files, largest peak RSS."""
    tried = [o for o in outcomes if o is not None and o.status is not None]
    if not tried:
        return "-"
    errors = sum(o.status != 0 and o.message.startswith("error:") for o in tried)
    tracebacks = sum(o.message.startswith("traceback") for o in tried)
    left = sum("leftovers:" in o.probe and "leftovers: none" not in o.probe for o in tried)
    peaks = [o.peak_rss_mb for o in tried if o.peak_rss_mb is not None]
    peak = f"{max(peaks):.0f} MB" if peaks else "-"
    return (
        f"{len(tried)} tried, {errors} one-line errors, {tracebacks} tracebacks, "
        f"{left} left files; peak RSS up to {peak}"
    )


def build_parser():
    parser = bench_parser(__doc__, "skip the multi-run cases", before=True)
    parser.add_argument("--only", metavar="GROUP", help="only this group: general, maps, commands")
    parser.add_argument("--out", type=Path, help="default: results/reliability[-GROUP].md")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    cases = [c for c in CASES if (c.quick or not args.quick) and args.only in (None, c.group)]
    with tempfile.TemporaryDirectory(prefix="bench-reliability-") as tmp:
        tmp_path = Path(tmp)
        before: list[Outcome | None] = [None] * len(cases)
        if args.before:
            with checkout(args.before) as before_tree:
                print(f"before ({args.before}):", file=sys.stderr)
                (tmp_path / "work-before").mkdir()
                before = run_cases(before_tree, cases, tmp_path / "work-before")
        print("after (this checkout):", file=sys.stderr)
        (tmp_path / "work-after").mkdir()
        after = run_cases(REPO, cases, tmp_path / "work-after")
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True,
                          text=True).stdout.strip()  # fmt: skip
    # without a before run its column would only hold dashes
    runs = [before, after] if args.before else [after]
    run_names = [f"before ({args.before})", "after"] if args.before else ["outcome"]
    lines = [
        "# Reliability cases" + (", before and after" if args.before else ""),
        "",
        f"`python benchmarks/bench_reliability.py{' --quick' if args.quick else ''}"
        f"{f' --only {args.only}' if args.only else ''}"
        f"{f' --before {args.before}' if args.before else ''}` at {head} (plus uncommitted "
        "changes, if any). Each cell: **exit code**, then the line that tells the user what "
        "happened (`error:` line, else the first warning, else the traceback's last line) and "
        f"[what a probe saw], cut at {CELL_MAX_CHARS} characters. Commands run on generated "
        "data in a temporary folder, whose path is left out of the messages.",
        "",
        *table(
            " | ".join(["#", "case", "command", *run_names]),
            (
                [c.number, c.title, f"`{c.command}`", *(cell(o[i]) for o in runs)]
                for i, c in enumerate(cases)
            ),
        ),
        "",
    ]
    names = dict.fromkeys(c.group for c in cases)
    groups = [[i for i, c in enumerate(cases) if c.group == name] for name in names]
    lines += table(
        " | ".join(["class", *run_names]),
        (
            [cases[pick[0]].group, *(class_summary([o[i] for i in pick]) for o in runs)]
            for pick in groups
        ),
    )
    if args.out is None:
        args.out = RESULTS_DIR / (f"reliability-{args.only}.md" if args.only else "reliability.md")
    write_text_atomic(args.out, "\n".join(lines) + "\n")
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
