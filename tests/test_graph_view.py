"""The main thread's view of the pose graph (slam/algorithm/graph_view.py): anchors predicted
from the odometry until their snapshot arrives, and snapshots applied incrementally ending in the
same state as a full rescan of every candidate."""

from __future__ import annotations

import numpy as np

from slam.algorithm.graph_view import GraphSnapshot, GraphView
from slam.algorithm.loops.base import LoopCandidate


def _translation(xyz) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = xyz
    return T


def _candidate(reference_id: int, query_id: int, accepted: bool) -> LoopCandidate:
    return LoopCandidate(
        reference_id, query_id, accepted, "accepted" if accepted else "rejected", np.eye(4), {}
    )


def test_anchors_opened_since_the_last_snapshot_follow_the_last_known_anchor() -> None:
    view = GraphView()
    odometry = {i: _translation([2.0 * i, 0.0, 0.0]) for i in range(3)}
    for i in range(3):
        view.add_anchor(i, odometry[i])
    np.testing.assert_array_equal(view.pose(2), odometry[2])  # nothing known: odometry
    corrected = _translation([0.0, 1.0, 0.0])  # the graph moved anchor 1 by 1 m in y
    view.apply(GraphSnapshot({0: odometry[0], 1: corrected @ odometry[1]}, [], {}, 0, True))
    np.testing.assert_allclose(view.pose(2)[:3, 3], [4.0, 1.0, 0.0])
    assert set(view.poses()) == {0, 1, 2}
    news = view.take_news()
    assert news[2] and view.take_news()[2] is False  # news are handed out once


def test_incremental_inlier_updates_give_the_state_of_a_full_rescan() -> None:
    rng = np.random.default_rng(0)
    view = GraphView()
    latest: dict[tuple[int, int], bool] = {}
    for job in range(60):
        candidates = [
            _candidate(int(rng.integers(0, job + 1)), job + 1, bool(rng.random() < 0.6))
            for _ in range(int(rng.integers(0, 4)))
        ]
        changed: dict[tuple[int, int], bool] = {}
        for c in candidates:
            if c.accepted:
                changed[(c.reference_id, c.query_id)] = c.graph_inlier = True
        for key in list(latest):  # GNC flips some older edges
            if rng.random() < 0.1:
                changed[key] = not latest[key]
        latest.update(changed)
        view.apply(GraphSnapshot({}, candidates, changed, len(latest), bool(changed)))
    # full rescan: every accepted candidate carries its edge's latest decision
    flipped = 0
    for c in view.loop_candidates:
        if c.accepted:
            assert c.graph_inlier == latest[(c.reference_id, c.query_id)]
            flipped += not c.graph_inlier
    assert flipped > 0 and view.num_accepted == len(latest)
