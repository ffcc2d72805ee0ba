"""GTSAM pose graph over submap anchors.

One node per submap anchor ``T_W_A``. Consecutive anchors are tied by odometry factors; loop
closures are ``BetweenFactorPose3``. Edge noise (``use_edge_covariances``): an edge that comes
with a covariance from its registration uses it, plus a floor (``loop_min_sigma_*``,
``odometry_min_sigma_*``) added in quadrature so that a very confident ICP cannot pin the graph.
Loop covariances come from the dense loop refinement or the LiDAR ICP (``factor * sigma^2 H^-1``
of the point-to-plane cost, :mod:`common.point_to_plane`); odometry covariances from
the RGB-D odometry's per-frame registration Hessians, chained from one anchor to the next. Edges
without one use the configured sigmas (odometry: growing with the distance travelled and the
angle turned).

Robust back-ends (``online_gnc``), each consistent from the first loop to the final estimate:

* GNC (default). A robust kernel alone cannot tell a wrong loop from a right one after large
  drift: both have a large residual at the odometry estimate. So every time a loop edge is added
  (rare compared to anchors) the whole graph is solved by graduated non-convexity (truncated least
  squares; prior and odometry factors known inliers), which starts from the convex least-squares
  problem and only then rejects edges that stay inconsistent. The GNC optimum *is* the estimate;
  iSAM2 is re-seeded with it and with the inlier loops as plain Gaussian factors (the GNC weights
  of inliers are 1, so the re-seeded problem has the same optimum), and only adds anchors on top
  until the next loop. Rejected loops stay in the record, are re-examined at every later GNC
  solve, and are reported. The final batch (``final_optimizer``): ``gnc`` solves once more;
  ``lm`` runs Levenberg-Marquardt on the chain and the *inlier* loops (Gaussian), so it never
  brings a rejected loop back.
* Cauchy (``online_gnc: false``): iSAM2 with every loop under a Cauchy kernel; the final ``lm``
  runs the same Cauchy problem in batch, ``gnc`` switches to GNC for the final estimate.

Gravity (``gravity.enabled``): a node ``G`` holds the gravity frame (its z axis is up; its heading
and position are fixed by a prior), and each submap whose walls give an up direction
(:mod:`slam.algorithm.graph.gravity`) gets a factor between ``G`` and its anchor that only
constrains the anchor's tilt (:mod:`slam.algorithm.graph.gravity_factors`). Like the prior and the
odometry, these are known inliers for GNC. G's tilt is held where the first measurement puts it:
the first anchor defines the world frame, and its own scan is the only up direction seen in that
frame without odometry in between. A free tilt let the odometry's attitude error between the
first anchors (KISS-ICP: 0.29 deg within the first 12 scans of the generated KITTI 00 street)
carry G, and every later anchor with it, away from the first scan's up. Where priors from a
stored map place the graph instead (:meth:`PoseGraph.reframe` with ``prior_sigmas``), the tilt
is free.

GTSAM orders the Pose3 tangent space as ``[rx, ry, rz, tx, ty, tz]``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np

from common.geometry import orthonormalize, rotation_angle_rad
from slam.algorithm.graph.config import PoseGraphConfig
from slam.algorithm.graph.gravity import UpMeasurement
from slam.algorithm.graph.gravity_factors import (
    GRAVITY_KEY,
    gravity_factor,
    gravity_frame_noise,
    gravity_frame_prior,
)
from slam.algorithm.graph.gtsam_poses import pose3, relative_pose_covariance

logger = logging.getLogger(__name__)

INLIER_WEIGHT = 0.5
"""A GNC weight above this keeps a loop edge."""
CAUCHY_INLIER_WEIGHT = 0.1
"""A Cauchy weight above this (whitened residual below 3 k) counts as an inlier."""
MAP_FRAME = -1
"""``LoopEdge.i`` of a map prior: the anchor ``j`` is measured in a stored map's fixed frame."""


@dataclass
class LoopEdge:
    """A loop edge: anchor ``j`` seen from anchor ``i`` (``T_Ai_Aj``), or, with ``i`` =
    :data:`MAP_FRAME`, a map prior: anchor ``j`` in a stored map's fixed frame.

    Attributes:
        weight: GNC weight (or Cauchy weight without GNC) at the latest solve; 1 = trusted.
        inlier: whether the edge is part of the current estimate.
        covariance: 6x6 covariance from the registration (``[rot, trans]``), or None.
    """

    i: int
    j: int
    T_Ai_Aj: np.ndarray
    sigma_scale: float = 1.0
    weight: float = 1.0
    inlier: bool = True
    covariance: np.ndarray | None = None


def _sigmas(rotation_rad: float, translation_m: float) -> np.ndarray:
    return np.array([rotation_rad] * 3 + [translation_m] * 3, dtype=np.float64)


class PoseGraph:
    """Submap-anchor pose graph: iSAM2 online, GNC at loop events and at the end."""

    def __init__(self, cfg: PoseGraphConfig) -> None:
        self.cfg = cfg
        self._isam = self._new_isam()
        self._chain: list[gtsam.NonlinearFactor] = []  # prior and odometry factors, in order
        self._gravity: list[gtsam.NonlinearFactor] = []  # G's prior, then one per measured anchor
        self._first_anchor_holds_frame = True  # until reframe() hands the frame to map priors
        self.up_measurements: dict[int, UpMeasurement] = {}
        self._node_ids: list[int] = []
        self._odometry_anchor: dict[int, np.ndarray] = {}
        self._estimate = gtsam.Values()
        self.loops: list[LoopEdge] = []
        self.map_priors: list[LoopEdge] = []  # each anchor in a stored map's frame (--map)

    def _new_isam(self) -> gtsam.ISAM2:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.cfg.isam2_relinearize_threshold)
        params.relinearizeSkip = 1
        return gtsam.ISAM2(params)

    # --- building the graph -------------------------------------------------------------------

    @property
    def node_ids(self) -> list[int]:
        """Ids of the anchors in the order they were added."""
        return list(self._node_ids)

    def __contains__(self, node_id: int) -> bool:
        return node_id in self._odometry_anchor

    def odometry_sigmas(self, distance_m: float, rotation_rad: float) -> np.ndarray:
        """Standard deviations ``[rx, ry, rz, tx, ty, tz]`` of an odometry edge."""
        c = self.cfg
        sigma_t = c.odometry_translation_sigma_m + c.odometry_translation_sigma_per_m * distance_m
        sigma_r = (
            c.odometry_rotation_sigma_rad
            + c.odometry_rotation_sigma_rad_per_m * distance_m
            + c.odometry_rotation_sigma_per_rad * rotation_rad
        )
        return _sigmas(sigma_r, sigma_t)

    def add_anchor(
        self, node_id: int, T_W_A_odometry: np.ndarray, covariance: np.ndarray | None = None
    ) -> None:
        """Add the anchor of a new submap with its odometry pose.

        The first anchor is fixed by a tight prior (it defines the world frame). Every later anchor
        gets an odometry factor from the previous one, measured by the odometry poses, and is
        initialised at the current estimate of the previous anchor composed with that measurement.
        ``covariance``: 6x6 (``[rot, trans]``) of that motion from the odometry's registrations,
        or None for the configured sigmas.
        """
        if node_id in self._odometry_anchor:
            raise ValueError(f"anchor {node_id} already in the pose graph")
        T_W_A_odometry = np.asarray(T_W_A_odometry, dtype=np.float64)
        new_values = gtsam.Values()
        if not self._node_ids:
            noise = gtsam.noiseModel.Diagonal.Sigmas(_sigmas(1e-6, 1e-6))
            factor = gtsam.PriorFactorPose3(node_id, pose3(T_W_A_odometry), noise)
            new_values.insert(node_id, pose3(T_W_A_odometry))
        else:
            prev = self._node_ids[-1]
            T_prev_cur = np.linalg.inv(self._odometry_anchor[prev]) @ T_W_A_odometry
            distance = float(np.linalg.norm(T_prev_cur[:3, 3]))
            angle = rotation_angle_rad(T_prev_cur[:3, :3])
            noise = self._odometry_noise(distance, angle, covariance)
            factor = gtsam.BetweenFactorPose3(prev, node_id, pose3(T_prev_cur), noise)
            new_values.insert(node_id, pose3(self.pose(prev) @ T_prev_cur))
        self._chain.append(factor)
        self._node_ids.append(node_id)
        self._odometry_anchor[node_id] = T_W_A_odometry
        new_factors = gtsam.NonlinearFactorGraph()
        new_factors.add(factor)
        self._isam.update(new_factors, new_values)
        self._estimate = self._isam.calculateEstimate()

    def _odometry_noise(
        self, distance_m: float, angle_rad: float, covariance: np.ndarray | None
    ) -> gtsam.noiseModel.Base:
        c = self.cfg
        if covariance is not None and c.use_edge_covariances:
            covariance = np.asarray(covariance, dtype=np.float64)
            if covariance.shape != (6, 6) or not np.all(np.isfinite(covariance)):
                raise ValueError("odometry covariance must be a finite 6x6 matrix")
            floor = _sigmas(c.odometry_min_sigma_rad, c.odometry_min_sigma_m) ** 2
            return gtsam.noiseModel.Gaussian.Covariance(covariance + np.diag(floor))
        return gtsam.noiseModel.Diagonal.Sigmas(self.odometry_sigmas(distance_m, angle_rad))

    def _loop_gaussian_noise(self, edge: LoopEdge) -> gtsam.noiseModel.Base:
        c = self.cfg
        if edge.covariance is not None and c.use_edge_covariances:
            floor = _sigmas(c.loop_min_sigma_rad, c.loop_min_sigma_m) ** 2
            covariance = edge.sigma_scale**2 * (edge.covariance + np.diag(floor))
            return gtsam.noiseModel.Gaussian.Covariance(covariance)
        return gtsam.noiseModel.Diagonal.Sigmas(
            edge.sigma_scale * _sigmas(c.loop_rotation_sigma_rad, c.loop_translation_sigma_m)
        )

    def _loop_factor(self, edge: LoopEdge, robust: bool) -> gtsam.NonlinearFactor:
        noise = self._loop_gaussian_noise(edge)
        if robust and self.cfg.loop_kernel == "cauchy":
            kernel = gtsam.noiseModel.mEstimator.Cauchy.Create(self.cfg.cauchy_k)
            noise = gtsam.noiseModel.Robust.Create(kernel, noise)
        if edge.i == MAP_FRAME:
            return gtsam.PriorFactorPose3(edge.j, pose3(edge.T_Ai_Aj), noise)
        return gtsam.BetweenFactorPose3(edge.i, edge.j, pose3(edge.T_Ai_Aj), noise)

    def _edges(self) -> list[LoopEdge]:
        """Every edge GNC may reject: the loops, then the map priors."""
        return [*self.loops, *self.map_priors]

    def add_loop(
        self,
        i: int,
        j: int,
        T_Ai_Aj: np.ndarray,
        sigma_scale: float = 1.0,
        covariance: np.ndarray | None = None,
    ) -> LoopEdge:
        """Add a verified loop edge between anchors ``i`` and ``j`` and re-solve.

        ``covariance``: 6x6 (``[rot, trans]``, right perturbation) from the registration, or
        None for the configured sigmas. Returns the edge; its ``inlier`` flag says whether the
        graph kept it.
        """
        covariance = self._checked(f"loop {i}-{j}", (i, j), covariance)
        edge = LoopEdge(
            i, j, np.asarray(T_Ai_Aj, dtype=np.float64).copy(), sigma_scale, covariance=covariance
        )
        self.loops.append(edge)
        self._add_edge(edge)
        return edge

    def add_map_prior(
        self, j: int, T_M_Aj: np.ndarray, covariance: np.ndarray | None = None
    ) -> LoopEdge:
        """Add a registration of anchor ``j`` to a stored map (its pose ``T_M_Aj`` in the map's
        frame, which must be the graph's world frame: :meth:`reframe` first) and re-solve.

        The stored map is fixed, so this is a prior on the anchor, judged by GNC like a loop
        (``covariance`` as for :meth:`add_loop`). Returns the edge (``i`` is
        :data:`MAP_FRAME`); its ``inlier`` flag says whether the graph kept it."""
        covariance = self._checked(f"map prior {j}", (j,), covariance)
        edge = LoopEdge(MAP_FRAME, j, orthonormalize(np.asarray(T_M_Aj)), covariance=covariance)
        self.map_priors.append(edge)
        self._add_edge(edge)
        return edge

    def _checked(
        self, name: str, nodes: tuple[int, ...], covariance: np.ndarray | None
    ) -> np.ndarray | None:
        """An edge's covariance as a float array, after checking it and its anchors."""
        for node in nodes:
            if node not in self._odometry_anchor:
                raise KeyError(f"anchor {node} is not in the pose graph")
        if covariance is None:
            return None
        covariance = np.asarray(covariance, dtype=np.float64)
        if covariance.shape != (6, 6) or not np.all(np.isfinite(covariance)):
            raise ValueError(f"{name}: covariance must be a finite 6x6 matrix")
        return covariance

    def _add_edge(self, edge: LoopEdge) -> None:
        if self.cfg.online_gnc:
            self._solve_gnc()
        else:
            new_factors = gtsam.NonlinearFactorGraph()
            new_factors.add(self._loop_factor(edge, robust=True))
            self._isam.update(new_factors, gtsam.Values())
            for _ in range(self.cfg.isam2_extra_iterations):
                self._isam.update()
            self._estimate = self._isam.calculateEstimate()
            self._update_cauchy_weights()

    def up_in(self, node_id: int) -> np.ndarray:
        """(3,) the up direction in an anchor's frame at the current estimate: the gravity
        frame's z axis, or the world's before the first up measurement."""
        R_W_A = self.pose(node_id)[:3, :3]
        up_W = np.array([0.0, 0.0, 1.0])
        if self._gravity:
            up_W = self._estimate.atPose3(GRAVITY_KEY).rotation().matrix()[:, 2]
        return R_W_A.T @ up_W

    def add_gravity(self, node_id: int, measurement: UpMeasurement) -> None:
        """Tie an anchor's tilt to the gravity frame by its measured up direction
        (:func:`gravity_factor`); the first call creates ``G`` (:func:`gravity_frame_prior`)."""
        if node_id not in self._odometry_anchor:
            raise KeyError(f"anchor {node_id} is not in the pose graph")
        new_factors = gtsam.NonlinearFactorGraph()
        new_values = gtsam.Values()
        T_W_A = self.pose(node_id)
        if not self._gravity:
            prior, T_W_G = gravity_frame_prior(
                GRAVITY_KEY, T_W_A, measurement, hold_tilt=self._first_anchor_holds_frame
            )
            self._gravity.append(prior)
            new_factors.add(prior)
            new_values.insert(GRAVITY_KEY, pose3(T_W_G))
        else:
            T_W_G = self._estimate.atPose3(GRAVITY_KEY).matrix()
        factor = gravity_factor(GRAVITY_KEY, node_id, T_W_G, T_W_A, measurement)
        self.up_measurements[node_id] = measurement
        self._gravity.append(factor)
        new_factors.add(factor)
        self._isam.update(new_factors, new_values)
        self._estimate = self._isam.calculateEstimate()

    def reframe(self, T_New_W: np.ndarray, prior_sigmas: tuple[float, float] | None = None) -> None:
        """Express the whole graph in another world frame: every anchor becomes
        ``T_New_W @ T_W_A`` and the first anchor's prior moves with it.

        A rigid change of frame leaves every relative measurement, hence every odometry and
        loop factor and the GNC inlier decisions, as they are; only the prior and the estimate
        change. Used when a session is relocalised in a stored map (``slam.run --map``).
        ``prior_sigmas`` (rad, m): loosen the first anchor's prior to these, when priors on the
        anchors in the new frame (:meth:`add_map_prior`) are to place the graph instead; the
        gravity frame's tilt is then free (now or when it is created), so that it follows the
        stored map's attitude.
        """
        if not self._node_ids:
            raise ValueError("reframe() before the first anchor")
        T_New_W = orthonormalize(np.asarray(T_New_W, dtype=np.float64))
        first = self._node_ids[0]
        prior = self._chain[0]
        T_W_A0 = prior.prior().matrix()
        noise = prior.noiseModel()
        if prior_sigmas is not None:
            noise = gtsam.noiseModel.Diagonal.Sigmas(_sigmas(*prior_sigmas))
            self._first_anchor_holds_frame = False
        self._chain[0] = gtsam.PriorFactorPose3(first, pose3(T_New_W @ T_W_A0), noise)
        moved = gtsam.Values()
        for node in self._node_ids:
            moved.insert(node, pose3(T_New_W @ self.pose(node)))
        if self._gravity:
            g_prior = self._gravity[0]
            g_noise = g_prior.noiseModel()
            if not self._first_anchor_holds_frame:
                g_noise = gravity_frame_noise(hold_tilt=False)
            self._gravity[0] = gtsam.PriorFactorPose3(
                GRAVITY_KEY, pose3(T_New_W @ g_prior.prior().matrix()), g_noise
            )
            T_W_G = self._estimate.atPose3(GRAVITY_KEY).matrix()
            moved.insert(GRAVITY_KEY, pose3(T_New_W @ T_W_G))
        self._reseed(moved)

    # --- solving ------------------------------------------------------------------------------

    def _known_inliers(self) -> gtsam.NonlinearFactorGraph:
        """Prior, odometry and gravity factors: never rejected."""
        graph = gtsam.NonlinearFactorGraph()
        for factor in (*self._chain, *self._gravity):
            graph.add(factor)
        return graph

    def _gaussian_graph(self) -> gtsam.NonlinearFactorGraph:
        graph = self._known_inliers()
        for edge in self._edges():
            graph.add(self._loop_factor(edge, robust=False))
        return graph

    def _solve_gnc(self) -> None:
        """GNC over the whole graph, then re-seed iSAM2 with the inlier loops and map priors."""
        if not self._edges():
            return
        params = gtsam.GncLMParams(gtsam.LevenbergMarquardtParams())
        params.setLossType(gtsam.GncLossType.TLS)
        known = len(self._chain) + len(self._gravity)
        params.setKnownInliers(list(range(known)))
        optimizer = gtsam.GncLMOptimizer(self._gaussian_graph(), self._estimate, params)
        optimizer.setInlierCostThresholdsAtProbability(self.cfg.gnc_inlier_probability)
        result = optimizer.optimize()
        weights = np.asarray(optimizer.getWeights(), dtype=np.float64)
        for edge, weight in zip(self._edges(), weights[known:], strict=True):
            edge.weight = float(weight)
            edge.inlier = bool(weight > INLIER_WEIGHT)
        self._reseed(result)

    def _inlier_graph(self) -> gtsam.NonlinearFactorGraph:
        """The known inliers and the GNC-inlier loops with Gaussian noise: the problem GNC
        solved."""
        graph = self._known_inliers()
        for edge in self._edges():
            if edge.inlier:
                graph.add(self._loop_factor(edge, robust=False))
        return graph

    def _online_graph(self) -> gtsam.NonlinearFactorGraph:
        """The problem the online back-end solves: with ``online_gnc`` the chain and the
        GNC-inlier loops (Gaussian), otherwise every loop under the Cauchy kernel."""
        if self.cfg.online_gnc:
            return self._inlier_graph()
        graph = self._known_inliers()
        for edge in self._edges():
            graph.add(self._loop_factor(edge, robust=True))
        return graph

    def _reseed(self, values: gtsam.Values) -> None:
        """Restart iSAM2 at ``values`` (the GNC optimum, or a reframed estimate) with the
        online problem."""
        self._isam = self._new_isam()
        self._isam.update(self._online_graph(), values)
        self._estimate = values

    def _update_cauchy_weights(self) -> None:
        for edge in self._edges():
            factor = self._loop_factor(edge, robust=False)
            whitened = float(np.linalg.norm(factor.whitenedError(self._estimate)))
            if self.cfg.loop_kernel == "cauchy":
                edge.weight = 1.0 / (1.0 + (whitened / self.cfg.cauchy_k) ** 2)
            else:
                edge.weight = 1.0
            edge.inlier = edge.weight > CAUCHY_INLIER_WEIGHT

    def optimize_batch(self) -> dict[int, np.ndarray]:
        """Optimise the whole graph from the current estimate (``cfg.final_optimizer``).

        ``gnc``: graduated non-convexity as at loop events. ``lm``: Levenberg-Marquardt on the
        problem of the online back-end: with ``online_gnc`` the chain and the GNC-inlier loops
        (Gaussian; rejected loops stay out), otherwise every loop under the Cauchy kernel.
        ``none``: keep the current estimate.
        """
        if not self._node_ids or not self._edges() or self.cfg.final_optimizer == "none":
            return self.poses()
        if self.cfg.final_optimizer == "gnc":
            self._solve_gnc()
            return self.poses()
        graph = self._online_graph()
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.cfg.batch_max_iterations)
        self._estimate = gtsam.LevenbergMarquardtOptimizer(graph, self._estimate, params).optimize()
        if not self.cfg.online_gnc:
            self._update_cauchy_weights()
        return self.poses()

    # --- reading the estimate -----------------------------------------------------------------

    def relative_covariance(self, i: int, j: int) -> np.ndarray:
        """6x6 marginal covariance (``[rot, trans]``) of ``T_Ai_Aj`` at the current estimate,
        from the chain and the inlier loops: the odometry's accumulated uncertainty between
        the two anchors where no loop ties them yet."""
        marginals = gtsam.Marginals(self._inlier_graph(), self._estimate)
        joint = marginals.jointMarginalCovariance(gtsam.KeyVector([i, j])).fullMatrix()
        return relative_pose_covariance(joint, self.pose(i), self.pose(j))

    def anchor_covariance(self, j: int) -> np.ndarray:
        """6x6 marginal covariance (``[rot, trans]``) of anchor ``j`` in the world frame at the
        current estimate, from the chain and the inlier edges."""
        marginals = gtsam.Marginals(self._inlier_graph(), self._estimate)
        return np.asarray(marginals.marginalCovariance(j), dtype=np.float64)

    def pose(self, node_id: int) -> np.ndarray:
        """Current estimate of ``T_W_A`` of one anchor."""
        return self._estimate.atPose3(node_id).matrix()

    def poses(self) -> dict[int, np.ndarray]:
        """Current estimate of every anchor, ``{node_id: T_W_A}``."""
        return {n: self._estimate.atPose3(n).matrix() for n in self._node_ids}

    def odometry_edges(self) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
        """The chain's odometry factors as ``(i, j, T_Ai_Aj, covariance)`` (the 6x6 covariance
        ``[rot, trans]`` of the noise the factor used, floors included), for a session record."""
        edges = []
        for factor in self._chain[1:]:
            i, j = (int(k) for k in factor.keys())
            covariance = np.asarray(factor.noiseModel().covariance(), dtype=np.float64)
            edges.append((i, j, factor.measured().matrix(), covariance))
        return edges

    def loop_covariance(self, edge: LoopEdge) -> np.ndarray:
        """6x6 covariance of the Gaussian noise a loop edge enters the graph with."""
        return np.asarray(self._loop_gaussian_noise(edge).covariance(), dtype=np.float64)
