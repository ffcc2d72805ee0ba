"""One thread budget sets torch, KISS-ICP, OpenCV and BLAS together."""

from __future__ import annotations

from pathlib import Path

import torch

from slam.assembly.config import RunConfig
from slam.assembly.threads import (
    apply_thread_budget,
    cgroup_cpu_quota,
    machine_cores,
    plan_thread_budget,
)


def test_plan_splits_the_budget() -> None:
    worker = plan_thread_budget(4, map_worker=True)
    assert (worker.torch, worker.kiss_icp, worker.opencv, worker.blas) == (3, 4, 4, 1)
    inline = plan_thread_budget(4, map_worker=False)
    assert inline.torch == 4
    assert plan_thread_budget(1, map_worker=True).torch == 1
    # the whole-map mesh after the run: the budget in units of torch's threads
    assert plan_thread_budget(2, map_worker=True).mesh_threads == 2
    assert plan_thread_budget(2, map_worker=False).mesh_threads == 1
    assert plan_thread_budget(1, map_worker=True).mesh_threads == 1
    assert plan_thread_budget(0, map_worker=False).budget == machine_cores()


def test_apply_sets_every_pool() -> None:
    import cv2
    from threadpoolctl import threadpool_info

    previous = (torch.get_num_threads(), cv2.getNumThreads())
    try:
        cfg = RunConfig.model_validate({"threads": 3, "map_worker": True})
        plan = apply_thread_budget(cfg)
        assert torch.get_num_threads() == plan.torch == 2
        assert cfg.odometry.kiss_icp.registration.max_num_threads == 3
        assert cv2.getNumThreads() == 3
        blas = [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]
        assert blas and all(n == 1 for n in blas)
        explicit = RunConfig.model_validate(
            {"threads": 3, "odometry": {"kiss_icp": {"registration": {"max_num_threads": 1}}}}
        )
        apply_thread_budget(explicit)
        assert (
            explicit.odometry.kiss_icp.registration.max_num_threads == 1
        )  # an explicit setting is kept
    finally:
        torch.set_num_threads(previous[0])
        cv2.setNumThreads(previous[1])


def test_the_cgroup_cpu_quota_caps_the_cores(tmp_path: Path) -> None:
    """A container's CPU limit (``docker --cpus``) in either cgroup version, whole CPUs."""
    v2 = tmp_path / "v2"
    v2.mkdir()
    (v2 / "cpu.max").write_text("250000 100000\n")
    assert cgroup_cpu_quota(v2) == 2
    (v2 / "cpu.max").write_text("50000 100000\n")
    assert cgroup_cpu_quota(v2) == 1  # half a CPU still gets one thread
    (v2 / "cpu.max").write_text("max 100000\n")
    assert cgroup_cpu_quota(v2) is None
    v1 = tmp_path / "v1"
    (v1 / "cpu").mkdir(parents=True)
    (v1 / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("300000\n")
    assert cgroup_cpu_quota(v1) == 3
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("-1\n")  # no limit
    assert cgroup_cpu_quota(v1) is None
    assert cgroup_cpu_quota(tmp_path / "missing") is None
    quota = cgroup_cpu_quota()
    assert 1 <= machine_cores() <= (quota or machine_cores())
