"""One CPU thread budget for every thread pool of a run.

A run has several native thread pools: torch's OpenMP pool (encoding, meshing), KISS-ICP's TBB
pool (registration), OpenCV's pool (RGB-D odometry, ORB) and the OpenBLAS pools of numpy and
scipy (every ``(N, 3) @ (3, 3)`` point transform). Each defaults to all cores and their idle
threads spin, so on a small machine they thrash each other: on 2 cores a 128k-point transform took
30 ms with OpenBLAS on 2 threads next to KISS-ICP, against 1 ms on one thread.
:func:`apply_thread_budget` sets them all from ``RunConfig.threads``: KISS-ICP and OpenCV get the
whole budget, torch gets the budget minus the odometry's share when the map runs on its own worker
thread (:mod:`slam.algorithm.map_worker`), and BLAS gets one thread (its matrices here are ``N x
3``).
"""

from __future__ import annotations

import contextlib
import logging
import os
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ThreadBudget:
    """Threads given to each pool (``budget`` is what they were derived from)."""

    budget: int
    torch: int
    kiss_icp: int
    opencv: int
    blas: int

    @property
    def mesh_threads(self) -> int:
        """Threads for the whole-map mesh after the run, when the map worker and the odometry
        are idle: the budget in units of torch's intra-op threads (each meshing thread runs
        torch with those)."""
        return max(1, self.budget // self.torch)

    def describe(self) -> str:
        return (
            f"budget {self.budget}: torch {self.torch}, KISS-ICP {self.kiss_icp}, "
            f"OpenCV {self.opencv}, BLAS {self.blas}"
        )


def cgroup_cpu_quota(root: Path = Path("/sys/fs/cgroup")) -> int | None:
    """Whole CPUs the cgroup's CPU quota allows this process (``docker --cpus``, a Kubernetes
    CPU limit), None where there is none.

    A container sees every core of its host in its affinity mask: with a quota of 2 on a
    64-core host, pools sized to the mask would spin 64 threads on 2 CPUs' time. Read from this
    process's cgroup (``/proc/self/cgroup``) and from the root that a container sees: cgroup v2
    ``cpu.max``, v1 ``cpu.cfs_quota_us`` over ``cpu.cfs_period_us``."""
    v2, v1 = [root], [root / "cpu"]
    with contextlib.suppress(OSError, ValueError):  # no /proc, or a line not id:controllers:path
        for line in Path("/proc/self/cgroup").read_text().splitlines():
            _, controllers, path = line.strip().split(":", 2)
            own = path.lstrip("/")
            if own and not controllers:
                v2.insert(0, root / own)
            elif own and "cpu" in controllers.split(","):
                v1.insert(0, root / "cpu" / own)
    for folder in v2:
        with contextlib.suppress(OSError, ValueError):
            quota, period = (folder / "cpu.max").read_text().split()[:2]
            if quota != "max":
                return max(1, int(quota) // int(period))
    for folder in v1:
        with contextlib.suppress(OSError, ValueError):
            quota_us = int((folder / "cpu.cfs_quota_us").read_text())
            period_us = int((folder / "cpu.cfs_period_us").read_text())
            if quota_us > 0 and period_us > 0:
                return max(1, quota_us // period_us)
    return None


def machine_cores() -> int:
    """Cores this process may run on: the affinity mask where the OS has one, capped by the
    cgroup's CPU quota (:func:`cgroup_cpu_quota`)."""
    if hasattr(os, "sched_getaffinity"):
        cores = max(1, len(os.sched_getaffinity(0)))
    else:
        cores = max(1, os.cpu_count() or 1)
    quota = cgroup_cpu_quota()
    return cores if quota is None else min(cores, quota)


def plan_thread_budget(threads: int, map_worker: bool) -> ThreadBudget:
    """The split of ``threads`` (0 = the machine's cores) between the pools."""
    budget = threads if threads > 0 else machine_cores()
    torch_threads = max(1, budget - 1) if map_worker else budget
    return ThreadBudget(budget=budget, torch=torch_threads, kiss_icp=budget, opencv=budget, blas=1)


def apply_thread_budget(cfg) -> ThreadBudget:
    """Set torch, OpenCV and BLAS threads and KISS-ICP's ``max_num_threads`` in ``cfg``.

    ``cfg`` is a :class:`slam.assembly.config.RunConfig`; its odometry settings are updated in
    place, so call this before the odometry is built. An explicit
    ``odometry.kiss_icp.registration.max_num_threads``
    (non-zero) is kept.
    """
    plan = plan_thread_budget(cfg.threads, cfg.map_worker)
    registration = cfg.odometry.kiss_icp.registration
    if not registration.max_num_threads:
        registration.max_num_threads = plan.kiss_icp
    return apply_plan(plan)


def apply_plan(plan: ThreadBudget) -> ThreadBudget:
    """Set torch's, OpenCV's and BLAS's threads to ``plan`` (what has no odometry, such as a
    merge, calls this alone)."""
    import torch

    torch.set_num_threads(plan.torch)
    try:
        import cv2

        cv2.setNumThreads(plan.opencv)
    except ImportError:  # OpenCV is only needed by the RGB-D front-end
        pass
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=plan.blas, user_api="blas")
    except ImportError:
        log.warning("BLAS threads left unset: pip install threadpoolctl")
    log.info("threads: %s", plan.describe())
    return plan
