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

import logging
import os
from dataclasses import dataclass

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


def machine_cores() -> int:
    """Cores this process may run on (the affinity mask where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


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
