"""LiDAR throughput: KISS-ICP alone, KISS-SLAM and ours on the same generated KITTI-00 scans.

    python -m benchmarks.bench_throughput [--frames N] [--label after] [--skip-kiss-slam] [--quick]
    python -m benchmarks.bench_throughput --report-only

The sequence is the 64-beam LiDAR simulated along all 4,541 poses of the real KITTI 00 trajectory
(2048 firings per revolution, cached by ``frontends.sources.generated``); ``--frames N`` runs the
first N scans (KISS-SLAM: ``--n-scans N``). Every method runs in its own
process, one after the other, so its peak memory is its own. Ours runs as ``slam.app.runner`` does
with
``--no-viz``: configs/kitti.yaml, the whole pipeline, the final optimisation, the final mesh and
``map.npz``; RSS is sampled at 1,000 / 2,000 / ... frames and at the end.

Results accumulate in ``benchmarks/results/throughput.json`` under ``--label`` (``before`` was
measured with the code of the commit before issue 11, by running this file with that checkout
first on PYTHONPATH); the report ``benchmarks/results/throughput.md`` shows all labels.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import datetime as dt
import json
import logging
import multiprocessing
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
KITTI_POSES = DATA / "kitti" / "poses" / "00.txt"
KITTI_CALIB = DATA / "kitti" / "sequences" / "00" / "calib.txt"
KISS_SLAM_VENV = Path("/tmp/kissslam-venv")
FULL_FRAMES = 4541
RSS_EVERY = 1000
QUICK_FRAMES = 300
RESULTS = REPO / "benchmarks" / "results" / "throughput.json"
REPORT = REPO / "benchmarks" / "results" / "throughput.md"
STAGES = (
    "odometry",
    "keyframing",
    "mapping",
    "loop_detection",
    "pose_graph",
    "remap",
    "map_logging",
    "final_mesh",
    "map_save",
)

log = logging.getLogger("benchmarks.bench_throughput")


def _rss_mb() -> tuple[float, float]:
    """(current, peak) resident memory of this process in MB."""
    current = peak = float("nan")
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                current = int(line.split()[1]) / 1024
            elif line.startswith("VmHWM:"):
                peak = int(line.split()[1]) / 1024
    return current, peak


def _source(num_frames: int, relief_m: float = 0.0):
    """The generated KITTI 00 scans (with hills of ``relief_m`` beside the road)."""
    from frontends.sources import make_source

    return make_source(
        "generated",
        kind="lidar",
        trajectory="kitti",
        kitti_poses=KITTI_POSES,
        kitti_calib=KITTI_CALIB,
        start=0,
        num_frames=FULL_FRAMES,
        step=1,
        azimuth_steps=2048,
        terrain_relief_m=relief_m,
        frames=slice(0, num_frames),
    )


def _config(extra: dict[str, Any] | None = None):
    """configs/kitti.yaml for the generated scans, without viewer, with ``extra`` on top."""
    from slam.app.config import default_config_path, load_run_config, merge_overrides

    overrides: dict[str, Any] = {
        "source": {"dataset": "generated"},
        "viz": {"mode": "none", "mesh_every_submaps": 10**9, "mesh_after_remap": False},
        "mapping": {"device": "cpu"},
    }
    return load_run_config(default_config_path("kitti"), merge_overrides(overrides, extra or {}))


def _apply_thread_budget(cfg) -> str:
    """The run's thread budget where this code has one (issue 11), else slam.app.runner's old
    setting."""
    try:
        from slam.app.threads import apply_thread_budget
    except ImportError:
        import torch

        torch.set_num_threads(cfg.torch_threads)
        kiss_threads = cfg.odometry.kiss_icp.registration.max_num_threads
        return f"torch {cfg.torch_threads}, KISS-ICP {kiss_threads or 'all'}"
    return apply_thread_budget(cfg).describe()


def scenario_ours(
    num_frames: int, override: dict[str, Any] | None = None, relief_m: float = 0.0
) -> dict:
    logging.basicConfig(level=logging.WARNING)
    from slam.algorithm.pipeline import SlamPipeline
    from slam.app.builders import build_map, build_odometry
    from slam.evaluation.metrics.trajectory import ate_per_axis_rmse, ate_rmse

    cfg = _config(override)
    threads = _apply_thread_budget(cfg)
    source = _source(num_frames, relief_m)
    odometry = build_odometry(cfg, "lidar")
    neural_map = build_map(cfg)
    pipeline = SlamPipeline(cfg.pipeline_config(), "lidar", odometry, neural_map)
    rss: dict[str, float] = {}
    start = time.perf_counter()
    cpu_start = time.process_time()
    main_cpu_start = time.thread_time()
    count = 0
    for frame in source.read_ahead():
        pipeline.process(frame)
        count += 1
        if count % RSS_EVERY == 0:
            rss[str(count)] = _rss_mb()[0]
    pipeline.finish()
    main_cpu_s = time.thread_time() - main_cpu_start
    mark = time.perf_counter()
    from slam.app.threads import plan_thread_budget

    mesh_threads = plan_thread_budget(cfg.threads, cfg.map_worker).mesh_threads
    mesh = neural_map.extract_mesh(threads=mesh_threads)
    final_mesh_s = time.perf_counter() - mark
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "map.npz"
        neural_map.save(path, list(pipeline.submaps.values()))
        map_bytes = path.stat().st_size
    wall = time.perf_counter() - start
    cpu_s = time.process_time() - cpu_start
    map_save_s = wall - final_mesh_s - (mark - start)
    rss[str(count)], peak_rss_mb = _rss_mb()  # before scoring: the run's own peak
    gt = source.gt_poses
    from slam.evaluation.metrics.trajectory import align_se3
    from slam.evaluation.run_metrics import mesh_errors

    errors = mesh_errors(
        mesh,
        source.gt_mesh_path,
        align_se3(pipeline.slam_poses(), gt),
        50_000,
        gt,
        lidar_range_m=cfg.submaps.max_range_m,
    )
    stage = {k: float(sum(v)) for k, v in pipeline.timings_s.items() if k != "frame"}
    stage.update(final_mesh=final_mesh_s, map_save=map_save_s)
    return {
        "frames": count,
        "wall_s": wall,
        "cpu_s": cpu_s,
        # main thread up to the end of finish(); the map worker's thread; the rest is KISS-ICP's
        # thread pool, reading ahead, the final mesh and the map file
        "cpu_threads_s": {"main": main_cpu_s, "map_worker": pipeline.worker.cpu_s},
        "fps": count / wall,
        "stage_s": stage,
        "stage_cpu_s": dict(pipeline.stage_cpu_s),
        "rss_mb": rss,
        "peak_rss_mb": peak_rss_mb,
        "peak_rss_with_scoring_mb": _rss_mb()[1],
        "map_npz_mb": map_bytes / 1e6,
        "map_voxels": neural_map.num_voxels,
        "submaps": len(pipeline.submaps),
        "loops_kept": sum(1 for c in pipeline.accepted_loops() if c.graph_inlier),
        "ate_odometry_m": ate_rmse(pipeline.odometry_poses(), gt),
        "ate_slam_m": ate_rmse(pipeline.slam_poses(), gt),
        "ate_xyz_odometry_m": ate_per_axis_rmse(pipeline.odometry_poses(), gt).tolist(),
        "ate_xyz_slam_m": ate_per_axis_rmse(pipeline.slam_poses(), gt).tolist(),
        "mesh_accuracy_m": errors["accuracy_m"],
        "mesh_faces": len(mesh.faces),
        "threads": threads,
    }


def scenario_kiss_icp(num_frames: int, relief_m: float = 0.0) -> dict:
    logging.basicConfig(level=logging.WARNING)
    from kiss_icp.kiss_icp import KissICP

    from slam.evaluation.metrics.trajectory import ate_per_axis_rmse, ate_rmse

    cfg = _config()
    threads = _apply_thread_budget(cfg)
    source = _source(num_frames, relief_m)
    kiss = KissICP(cfg.odometry.kiss_icp.to_kiss())
    poses = []
    start = time.perf_counter()
    cpu_start = time.process_time()
    for frame in source:
        kiss.register_frame(np.asarray(frame.points, dtype=np.float64), np.zeros(0))
        poses.append(np.array(kiss.last_pose))
    wall = time.perf_counter() - start
    return {
        "frames": len(poses),
        "wall_s": wall,
        "cpu_s": time.process_time() - cpu_start,
        "fps": len(poses) / wall,
        "peak_rss_mb": _rss_mb()[1],
        "ate_odometry_m": ate_rmse(np.array(poses), source.gt_poses),
        "ate_xyz_odometry_m": ate_per_axis_rmse(np.array(poses), source.gt_poses).tolist(),
        "threads": threads,
    }


def scenario_kiss_slam(num_frames: int, relief_m: float = 0.0) -> dict:
    python = KISS_SLAM_VENV / "bin" / "python"
    if not python.is_file():
        return {"skipped": f"no KISS-SLAM venv at {KISS_SLAM_VENV}"}
    from slam.app.trajectory_io import read_kitti
    from slam.evaluation.metrics.trajectory import ate_per_axis_rmse, ate_rmse

    source = _source(num_frames, relief_m)
    root = Path(source.sequence_dir).parents[1]
    with tempfile.TemporaryDirectory() as work:
        start = time.perf_counter()
        run = subprocess.run(
            [
                "/usr/bin/time",
                "-f",
                "MAXRSS_KB %M\nCPU_S %U %S",
                str(KISS_SLAM_VENV / "bin" / "kiss_slam_pipeline"),
                str(root),
                "--dataloader",
                "kitti",
                "--sequence",
                "00",
                "--n-scans",
                str(num_frames),
            ],
            cwd=work,
            capture_output=True,
            text=True,
            timeout=4 * 3600,
        )
        wall = time.perf_counter() - start
        if run.returncode != 0:
            said = [
                line
                for line in (run.stderr + run.stdout).strip().splitlines()
                if not line.startswith(("MAXRSS_KB", "CPU_S", "Command exited"))
            ]
            return {"skipped": f"KISS-SLAM exited with {run.returncode}: {(said or ['?'])[-1]}"}
        found = sorted(Path(work).rglob("*_poses_kitti.txt"))
        if not found:
            return {"skipped": "KISS-SLAM wrote no poses file"}
        poses = read_kitti(found[0])
    peak = cpu_s = None
    for line in run.stderr.splitlines():
        if line.startswith("MAXRSS_KB"):
            peak = int(line.split()[1]) / 1024
        elif line.startswith("CPU_S"):
            cpu_s = sum(float(v) for v in line.split()[1:])
    return {
        "frames": len(poses),
        "wall_s": wall,
        "cpu_s": cpu_s,
        "fps": len(poses) / wall,
        "peak_rss_mb": peak,
        "ate_slam_m": ate_rmse(poses, source.gt_poses[: len(poses)]),
        "ate_xyz_slam_m": ate_per_axis_rmse(poses, source.gt_poses[: len(poses)]).tolist(),
    }


def scenario_micro(_: int) -> dict:
    """Encode one 30k-point depth frame with Jacobians: by the encoder network over every pair
    and over the default Jacobian sample, and by the encoder's latent table (the default; its
    build time and its per-voxel relative difference to the network); mesh a ~20k-voxel room map
    from cold (1 thread, and 2)."""
    import torch

    from benchmarks.bench_mapping import V, depth_frame_points, room_mesh, sample_surface
    from mapping.config import MapConfig
    from mapping.encoding import encode_points
    from mapping.latent_table import latent_table
    from mapping.networks import load_default_prior
    from mapping.neural_map import NeuralMap

    def timed(fn, repeats: int = 15) -> tuple[float, float]:
        walls, cpus = [], []
        for _ in range(repeats):
            t, c = time.perf_counter(), time.process_time()
            fn()
            walls.append(time.perf_counter() - t)
            cpus.append(time.process_time() - c)
        return float(np.median(walls)), float(np.median(cpus))

    def rel_errors(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Per-voxel relative difference of ``a`` to ``b``."""
        scale = b.flatten(1).norm(dim=1).clamp_min(1e-12)
        return (a - b).flatten(1).norm(dim=1) / scale

    model = load_default_prior().eval()
    room = room_mesh((5.0, 4.0, 2.6))
    points, normals, _ = depth_frame_points(room, keep=30000)
    p, n = torch.from_numpy(points), torch.from_numpy(normals)
    out: dict[str, Any] = {"encode_points": len(points)}
    for threads in (1, 2):
        torch.set_num_threads(threads)
        block = encode_points(model, p, n, V)
        wall, cpu = timed(lambda: encode_points(model, p, n, V))
        out[f"encode_wall_s_{threads}t"], out[f"encode_cpu_s_{threads}t"] = wall, cpu
    out["encode_voxels"] = block.num_voxels
    torch.set_num_threads(1)
    out["encode_nojac_wall_s_1t"] = timed(
        lambda: encode_points(model, p, n, V, with_jacobian=False)
    )[0]
    cap = MapConfig().jacobian_pairs_per_voxel
    capped = encode_points(model, p, n, V, jacobian_pairs_per_voxel=cap)
    out["encode_capped_pairs"] = cap
    out["encode_capped_jacobian_rel_diff_median"] = float(
        rel_errors(capped.jacobians, block.jacobians).median()
    )
    for threads in (1, 2):
        torch.set_num_threads(threads)
        out[f"encode_capped_wall_s_{threads}t"], out[f"encode_capped_cpu_s_{threads}t"] = timed(
            lambda: encode_points(model, p, n, V, jacobian_pairs_per_voxel=cap)
        )
    # the product's default: the encoder's latent table (built once per process, timed here)
    nodes = MapConfig().encoder_table_nodes
    torch.set_num_threads(1)
    t = time.perf_counter()
    latent_table(model.encoder, nodes)
    out["encode_table_nodes"] = nodes
    out["encode_table_build_s"] = time.perf_counter() - t
    looked_up = encode_points(model, p, n, V, jacobian_pairs_per_voxel=cap, table_nodes=nodes)
    for name, a, b in (
        ("latent", looked_up.latents, capped.latents),
        ("jacobian", looked_up.jacobians, capped.jacobians),
    ):
        error = rel_errors(a, b)
        out[f"encode_table_{name}_rel_diff_median"] = float(error.median())
        out[f"encode_table_{name}_rel_diff_max"] = float(error.max())
    for threads in (1, 2):
        torch.set_num_threads(threads)
        out[f"encode_table_wall_s_{threads}t"], out[f"encode_table_cpu_s_{threads}t"] = timed(
            lambda: encode_points(model, p, n, V, jacobian_pairs_per_voxel=cap, table_nodes=nodes)
        )
    cfg = MapConfig(min_points_per_voxel=1, min_weight_to_decode=4.0, device="cpu")
    surface, surface_normals = sample_surface(room, 1500, seed=1)
    submap = NeuralMap(cfg, model).encode(0, surface, surface_normals, np.eye(4))
    torch.set_num_threads(1)
    neural_map = NeuralMap(cfg, model)
    neural_map.fuse(submap)
    t, c = time.perf_counter(), time.process_time()
    mesh = neural_map.extract_mesh()
    out["mesh_cold_wall_s"] = time.perf_counter() - t
    out["mesh_cold_cpu_s"] = time.process_time() - c
    out["mesh_voxels"] = neural_map.num_voxels
    out["mesh_faces"] = len(mesh.faces)
    t = time.perf_counter()
    neural_map.extract_mesh()
    out["mesh_again_wall_s"] = time.perf_counter() - t
    # from cold on the whole 2-thread budget, as the final mesh of a run (torch 1 thread each)
    submap.fused = False
    neural_map = NeuralMap(cfg, model)
    neural_map.fuse(submap)
    t, c = time.perf_counter(), time.process_time()
    neural_map.extract_mesh(threads=2)
    out["mesh_cold_wall_s_2t"] = time.perf_counter() - t
    out["mesh_cold_cpu_s_2t"] = time.process_time() - c
    out["load"] = os.getloadavg()[0]
    return out


def scenario_rgbd(_: int) -> dict:
    """bench_slam's RGB-D scenarios (generated room with the demo config, 7-Scenes 0-399), with
    this code's thread budget where it has one."""
    from benchmarks import bench_slam

    _apply_thread_budget(_config())
    keep = (
        "frames",
        "fps",
        "wall_s",
        "ate_odometry_m",
        "ate_slam_m",
        "mesh_accuracy_m",
        "mesh_completion_m",
        "stage_s",
        "peak_rss_mb",
    )
    out = {}
    for name, fn in (("room", bench_slam.scenario_room), ("7scenes", bench_slam.scenario_7scenes)):
        r = fn()
        out[name] = None if r is None else {k: r.get(k) for k in keep}
    out["load"] = os.getloadavg()[0]
    return out


def _in_child(fn, *args):
    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(max_workers=1, mp_context=context) as pool:
        return pool.submit(fn, *args).result()


# --------------------------------------------------------------------------- report


def _f(value, digits: int = 1) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "n/a"
    return f"{value:.{digits}f}"


def write_report(results: dict) -> None:
    lines = [
        "## LiDAR throughput (issue 11)",
        "",
        "Generated 64-beam LiDAR along the real KITTI 00 trajectory (2048 firings per revolution, "
        "~128k points per scan), configs/kitti.yaml, `NullLogger` (as `--no-viz`), CPU only, "
        "2 cores shared with other jobs (the load average is part of each row). Ours includes "
        "reading the scans, the final optimisation, the final mesh and writing `map.npz`; "
        "KISS-ICP alone is reading + `register_frame`; KISS-SLAM is its `kiss_slam_pipeline` "
        "process (0.0.2, default config). Ours' peak RSS is taken before its mesh is scored "
        "against ground truth (evaluation, not SLAM; `peak_rss_with_scoring_mb` in "
        "throughput.json). CPU = user + system time of all the method's threads (where "
        "recorded): on two cores that are both busy, the wall time is about half of it, and it "
        "varies less between runs than the wall time.",
        "",
        "| run | code | frames | method | wall [s] | CPU [s] | frames/s | vs KISS-ICP | "
        "vs KISS-SLAM | peak RSS [MB] | ATE odometry [m] | ATE SLAM [m] | load |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for key in sorted(results):
        run = results[key]
        icp = run.get("kiss_icp") or {}
        kslam = run.get("kiss_slam") or {}
        for name in ("kiss_icp", "kiss_slam", "ours"):
            r = run.get(name)
            if not r or "skipped" in r or "frames" not in r:
                continue
            vs_icp = r["wall_s"] / icp["wall_s"] if icp.get("wall_s") else None
            vs_slam = r["wall_s"] / kslam["wall_s"] if kslam.get("wall_s") else None
            lines.append(
                f"| {key} | {run['code']} | {r['frames']} | {name} | {_f(r['wall_s'])} | "
                f"{_f(r.get('cpu_s'), 0)} | {_f(r['fps'], 2)} | {_f(vs_icp, 2)} | "
                f"{_f(vs_slam, 2)} | "
                f"{_f(r.get('peak_rss_mb'), 0)} | {_f(r.get('ate_odometry_m'), 3)} | "
                f"{_f(r.get('ate_slam_m'), 3)} | {_f(run.get('load'), 1)} |"
            )
    lines += _per_axis_lines(results)
    lines += [
        "",
        "Ours, per stage [s] (`map_logging` is the null logger's share; with the map worker, "
        "mapping and remap run on a second thread, overlapped with odometry, so the stages can "
        "add up to more than the whole run; CPU: the main thread's CPU time to the end of the "
        "final remap, the map worker thread's, and the rest of the process (KISS-ICP's thread "
        "pool, reading ahead, the final mesh, writing the map); `final_mesh` is the whole map "
        "meshed after the last remap (on the whole thread budget) and `map_save` writing "
        "`map.npz`, both after the last frame; n/a: not timed then), memory and map:",
        "",
        "| run | " + " | ".join(STAGES) + " | whole run | CPU main / map worker / other [s] | "
        f"RSS at {RSS_EVERY:,}-frame steps [MB] | map.npz [MB] | voxels | mesh accuracy [cm] | "
        "threads |",
        "|---|" + "---|" * (len(STAGES) + 7),
    ]
    for key in sorted(results):
        r = results[key].get("ours")
        if not r:
            continue
        cells = [_f(r["stage_s"].get(s)) for s in STAGES]
        rss = ", ".join(f"{k}: {v:.0f}" for k, v in r["rss_mb"].items())
        threads = r.get("cpu_threads_s")
        if threads:
            other = r["cpu_s"] - threads["main"] - threads["map_worker"]
            cpu = f"{threads['main']:.0f} / {threads['map_worker']:.0f} / {other:.0f}"
        else:
            cpu = "n/a"
        lines.append(
            f"| {key} | " + " | ".join(cells) + f" | {_f(r['wall_s'])} | {cpu} | {rss} | "
            f"{r['map_npz_mb']:.1f} | {r['map_voxels']:,} | {100 * r['mesh_accuracy_m']:.2f} | "
            f"{r['threads']} |"
        )
    shares = [k for k in sorted(results) if (results[k].get("ours") or {}).get("stage_cpu_s")]
    if shares:
        lines += [
            "",
            "Ours, the stages' shares of the run: CPU seconds of the thread that ran each stage "
            "(the map worker's for mapping and remap; KISS-ICP's own thread pool is not in "
            "odometry's), as a share of the run's wall time and of its CPU time. A stage on the "
            "map worker overlaps the main thread, so its wall time there is mostly waiting for "
            "a core; `map_worker_wait` is what the main thread lost waiting for the worker.",
            "",
            "| run | stage | wall [s] | CPU [s] | CPU / run wall | CPU / run CPU |",
            "|---|---|---|---|---|---|",
        ]
        for key in shares:
            r = results[key]["ours"]
            stage_s = dict(r["stage_s"])
            cpu = r["stage_cpu_s"]
            for stage in (*STAGES, "map_worker_wait"):
                if stage not in cpu:
                    continue
                lines.append(
                    f"| {key} | {stage} | {_f(stage_s.get(stage))} | {cpu[stage]:.1f} | "
                    f"{100 * cpu[stage] / r['wall_s']:.0f} % | "
                    f"{100 * cpu[stage] / r['cpu_s']:.0f} % |"
                )
    lines += [
        "",
        "Micro-benchmarks (`--only micro`): one 640x480 depth frame of the benchmark room "
        "subsampled to 30,000 points, encoded with Jacobians (V = 0.1 m; median of 5 runs before "
        "stop 19, of 15 since); a room map meshed from cold (first `extract_mesh`, torch on 1 "
        "thread; and on two Python threads of one torch thread each) and again unchanged.",
        "",
        "| run | encode, 1 thread [s] (CPU s) | frames/s | encode, 2 threads [s] | "
        "mesh voxels | mesh cold [s] (CPU s) | mesh cold, 2 threads [s] | mesh again [s] | "
        "load |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for key in sorted(results):
        m = results[key].get("micro")
        if not m:
            continue
        lines.append(
            f"| {key} | {m['encode_wall_s_1t']:.3f} ({m['encode_cpu_s_1t']:.3f}) | "
            f"{1 / m['encode_wall_s_1t']:.2f} | {m['encode_wall_s_2t']:.3f} | "
            f"{m['mesh_voxels']:,} | {m['mesh_cold_wall_s']:.2f} ({m['mesh_cold_cpu_s']:.2f}) | "
            f"{_f(m.get('mesh_cold_wall_s_2t'), 2)} | {m['mesh_again_wall_s']:.3f} | "
            f"{m['load']:.1f} |"
        )
    compiled = [
        k for k in sorted(results) if "encode_compiled_wall_s_1t" in results[k].get("micro", {})
    ]
    if compiled:
        lines += [
            "",
            "The same frame through `encode_points(..., compiled=True)` (torch.compile, inductor; "
            "removed at stop 20, where the latent table made it redundant): the first call "
            "includes compiling (shorter when inductor's on-disk cache is warm); "
            "rel. diff = largest per-voxel relative difference to the eager result.",
            "",
            "| run | encode no Jacobian, 1 thread [s] | compiled first call [s] | "
            "compiled, 1 thread [s] (CPU s) | frames/s | compiled, 2 threads [s] | "
            "rel. diff latents / Jacobians | load |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for key in compiled:
            m = results[key]["micro"]
            lines.append(
                f"| {key} | {m['encode_nojac_wall_s_1t']:.3f} | "
                f"{m['encode_compiled_first_call_s']:.1f} | "
                f"{m['encode_compiled_wall_s_1t']:.3f} ({m['encode_compiled_cpu_s_1t']:.3f}) | "
                f"{1 / m['encode_compiled_wall_s_1t']:.2f} | "
                f"{m['encode_compiled_wall_s_2t']:.3f} | "
                f"{m['encode_compiled_latent_rel_diff']:.1e} / "
                f"{m['encode_compiled_jacobian_rel_diff']:.1e} | {m['load']:.1f} |"
            )
    capped = [
        k for k in sorted(results) if "encode_capped_wall_s_1t" in results[k].get("micro", {})
    ]
    if capped:
        lines += [
            "",
            "The same frame with each voxel's Jacobian taken from at most "
            "`mapping.jacobian_pairs_per_voxel` of its point-voxel pairs (the default since stop "
            "17; the latents still use every pair): rel. diff = median per-voxel relative "
            "difference of the Jacobians to those of every pair.",
            "",
            "| run | pairs | eager, 1 thread [s] (CPU s) | frames/s | eager, 2 threads [s] | "
            "frames/s | compiled, 1 thread [s] | frames/s | Jacobian rel. diff (median) | load |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for key in capped:
            m = results[key]["micro"]
            two = m.get("encode_capped_wall_s_2t")
            compiled = m.get("encode_capped_compiled_wall_s_1t")
            lines.append(
                f"| {key} | {m['encode_capped_pairs']} | {m['encode_capped_wall_s_1t']:.3f} "
                f"({m['encode_capped_cpu_s_1t']:.3f}) | {1 / m['encode_capped_wall_s_1t']:.2f} | "
                f"{_f(two, 3)} | {_f(None if two is None else 1 / two, 2)} | "
                f"{_f(compiled, 3)} | {_f(None if compiled is None else 1 / compiled, 2)} | "
                f"{m['encode_capped_jacobian_rel_diff_median']:.3f} | {m['load']:.1f} |"
            )
    tables = [k for k in sorted(results) if "encode_table_wall_s_1t" in results[k].get("micro", {})]
    if tables:
        lines += [
            "",
            "The same frame, with the same Jacobian sample, by lookup in the encoder's latent "
            "table (`mapping.encoder_table_nodes`, the default since stop 20) instead of the "
            "network: build = building the table, once per process; rel. diff = per-voxel "
            "relative difference to the network's latents and Jacobians (median / max).",
            "",
            "| run | nodes | build [s] | 1 thread [s] (CPU s) | frames/s | 2 threads [s] | "
            "frames/s | latents rel. diff | Jacobians rel. diff | load |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for key in tables:
            m = results[key]["micro"]
            one, two = m["encode_table_wall_s_1t"], m["encode_table_wall_s_2t"]
            lines.append(
                f"| {key} | {m['encode_table_nodes']} | {m['encode_table_build_s']:.2f} | "
                f"{one:.3f} ({m['encode_table_cpu_s_1t']:.3f}) | {1 / one:.1f} | {two:.3f} | "
                f"{1 / two:.1f} | {m['encode_table_latent_rel_diff_median']:.1e} / "
                f"{m['encode_table_latent_rel_diff_max']:.1e} | "
                f"{m['encode_table_jacobian_rel_diff_median']:.1e} / "
                f"{m['encode_table_jacobian_rel_diff_max']:.1e} | {m['load']:.1f} |"
            )
    lines += _rgbd_lines(results)
    lines.append("")
    REPORT.parent.mkdir(parents=True, exist_ok=True)
    REPORT.write_text("\n".join(lines))


def _per_axis_lines(results: dict) -> list[str]:
    """Per-axis ATE (RMSE along world x, y, z after the SE(3) alignment) where recorded."""
    rows = []
    for key in sorted(results):
        for name in ("kiss_icp", "kiss_slam", "ours"):
            r = results[key].get(name) or {}
            odometry, slam = r.get("ate_xyz_odometry_m"), r.get("ate_xyz_slam_m")
            if odometry is None and slam is None:
                continue
            cells = [
                "n/a" if xyz is None else " / ".join(f"{v:.3f}" for v in xyz)
                for xyz in (odometry, slam)
            ]
            rows.append(f"| {key} | {name} | {cells[0]} | {cells[1]} |")
    if not rows:
        return []
    return [
        "",
        "Per-axis ATE [m] (x / y / z, z up; issue 12's vertical drift), where recorded:",
        "",
        "| run | method | odometry x / y / z | SLAM x / y / z |",
        "|---|---|---|---|",
        *rows,
    ]


def _rgbd_lines(results: dict) -> list[str]:
    """The RGB-D table of ``--only rgbd`` runs; nothing when there are none."""
    rows = []
    for key in sorted(results):
        rgbd = results[key].get("rgbd")
        if not rgbd:
            continue
        for name in ("room", "7scenes"):
            r = rgbd.get(name)
            if not r:
                continue
            accuracy = r.get("mesh_accuracy_m")
            rows.append(
                f"| {key} | {name} | {r['frames']} | {r['fps']:.2f} | "
                f"{r['ate_odometry_m']:.4f} | {r['ate_slam_m']:.4f} | "
                f"{'n/a' if accuracy is None else f'{100 * accuracy:.2f}'} | "
                f"{r['peak_rss_mb']:.0f} | {rgbd['load']:.1f} |"
            )
    if not rows:
        return []
    return [
        "",
        "RGB-D (`--only rgbd`: bench_slam's room and 7-Scenes scenarios, `NullLogger`):",
        "",
        "| run | sequence | frames | frames/s | ATE odometry [m] | ATE SLAM [m] | "
        "mesh accuracy [cm] | peak RSS [MB] | load |",
        "|---|---|---|---|---|---|---|---|---|",
        *rows,
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=FULL_FRAMES, help="first N scans")
    parser.add_argument("--label", default="after", help="code label of this run")
    parser.add_argument(
        "--only", choices=["ours", "kiss_icp", "kiss_slam", "micro", "rgbd"], action="append"
    )
    parser.add_argument("--skip-kiss-slam", action="store_true")
    parser.add_argument(
        "--override",
        type=json.loads,
        default=None,
        help="config overrides for ours, as JSON (e.g. "
        '\'{"mapping": {"jacobian_pairs_per_voxel": 0}}\'); recorded with the run',
    )
    parser.add_argument(
        "--relief",
        type=float,
        default=0.0,
        help="height of the hills beside the road, metres (generated.terrain_relief_m; "
        "the scans are generated on first use)",
    )
    parser.add_argument("--report-only", action="store_true")
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"the first {QUICK_FRAMES} scans, KISS-ICP and ours only (run_all --quick)",
    )
    args = parser.parse_args(argv)
    if args.quick:
        args.frames = min(args.frames, QUICK_FRAMES)
        args.skip_kiss_slam = True
    results = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {}
    if not args.report_only:
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
        hills = f"{args.relief:g} m hills, " if args.relief else ""
        key = f"{args.frames} frames, {hills}{args.label}"
        run = results.get(key, {})
        run.update(
            code=args.label,
            date=dt.datetime.now().isoformat(timespec="seconds"),
            load=os.getloadavg()[0],
        )
        if args.override:
            run["override"] = args.override
        methods = args.only or ["kiss_icp", "kiss_slam", "ours"]
        if args.skip_kiss_slam and "kiss_slam" in methods:
            methods.remove("kiss_slam")
        for name in methods:
            log.info("%s, %d frames", name, args.frames)
            if name == "kiss_slam":
                run[name] = scenario_kiss_slam(args.frames, args.relief)
            else:
                fn = {
                    "ours": scenario_ours,
                    "kiss_icp": scenario_kiss_icp,
                    "micro": scenario_micro,
                    "rgbd": scenario_rgbd,
                }[name]
                extra = {"ours": (args.override, args.relief), "kiss_icp": (args.relief,)}
                extra = extra.get(name, ())
                run[name] = _in_child(fn, args.frames, *extra)
            log.info("%s: %s", name, {k: v for k, v in run[name].items() if k != "stage_s"})
            # re-read before writing: several invocations may run side by side
            results = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {}
            merged = results.setdefault(key, {})
            fields = ("code", "date", "load", "override", name)
            merged.update({k: run[k] for k in fields if k in run})
            RESULTS.parent.mkdir(parents=True, exist_ok=True)
            RESULTS.write_text(json.dumps(results, indent=2, default=str))
    write_report(results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
