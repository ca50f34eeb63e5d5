"""Robust pose-graph optimisation over the keyframes (or all frames) of a group of agents.

Nodes are camera poses ``T_world_cam`` in the group frame; sequential edges come from each
agent's tracking (trusted, Gaussian), loop edges from registration (wrapped in a robust kernel,
or handled by graduated non-convexity, so that a false loop cannot bend the map). Each
connected component of the graph is anchored at its first node. After optimisation every loop
is classified inlier/outlier by a chi-square test on its whitened residual.

Two ways to cover the ordinary frames (``all_frames``):

- keyframes only: nodes are keyframes; a sequential edge spanning ``n`` tracked frames gets
  its per-frame sigmas times ``sqrt(n)``; frames follow their keyframe afterwards
  (``correct_frames``: ``T_world_frame = T_world_kf_new @ T_kf_frame``).
- all frames (the paper): every frame is a node, chained frame to frame; slower, and the
  frames between keyframes can bend with the correction instead of moving rigidly.

Noise sigmas are given in our order (translation metres, then rotation radians) and so is an
information matrix passed to ``add_loop`` (the g2o order); gtsam's Pose3 tangent is rotation
first, the conversion happens in the solver. See docs/pose_graph.md.

This module builds the graph; ``cpslam.server.solver`` optimises it with gtsam and classifies
the loops, ``cpslam.server.trajectory`` holds an agent's track as the graph takes it and
``cpslam.server.g2o`` writes the graph to a file. Every name in ``__all__`` can be imported from
here.
"""

from __future__ import annotations

import logging
from collections.abc import Hashable
from itertools import pairwise
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cpslam.common.geometry import compose, invert, is_rigid
from cpslam.server.g2o import write_g2o
from cpslam.server.solver import CHI2_6DOF_95, Edge, PoseGraphResult, RobustKernel, solve
from cpslam.server.solver import Node as Node  # re-exported: the key type of the result's poses
from cpslam.server.trajectory import AgentTrajectory, check_shape, correct_frames, frame_chain

if TYPE_CHECKING:
    from cpslam.common.config.collab import PoseGraphConfig

__all__ = [
    "CHI2_6DOF_95",
    "AgentTrajectory",
    "PoseGraph",
    "PoseGraphResult",
    "correct_frames",
    "loop_sigmas",
]

logger = logging.getLogger(__name__)


def loop_sigmas(
    sigma_t: float,
    sigma_r: float,
    residual_m: float,
    overlap: float,
    ref_residual_m: float = 0.01,
) -> tuple[float, float]:
    """Loop-edge sigmas ``(sigma_t, sigma_r)`` from registration quality.

    ``residual_m`` is the mean depth residual after registration and ``overlap`` the fraction
    of pixels that overlapped the other map. A residual above the sensor floor
    ``ref_residual_m`` means the alignment is off by about that much, so the sigmas grow
    linearly with it; fewer overlapping pixels are fewer independent measurements, so the
    sigmas grow as ``1 / sqrt(overlap)``.
    """
    if not 0.0 < overlap <= 1.0:
        raise ValueError(f"loop_sigmas: overlap must be in (0, 1], got {overlap}")
    if residual_m < 0 or ref_residual_m <= 0:
        raise ValueError(f"loop_sigmas: residual {residual_m} / reference {ref_residual_m}")
    scale = max(1.0, residual_m / ref_residual_m) / np.sqrt(overlap)
    return sigma_t * scale, sigma_r * scale


class PoseGraph:
    """Keyframes of one or more agents, tracking and loop edges, and their optimisation."""

    def __init__(
        self,
        *,
        robust_kernel: RobustKernel,
        kernel_scale: float,
        seq_sigma_t: float,
        seq_sigma_r: float,
        loop_sigma_t: float,
        loop_sigma_r: float,
        max_iters: int,
        rel_tol: float,
        all_frames: bool,
    ) -> None:
        if robust_kernel not in ("cauchy", "huber", "gnc", "none"):
            raise ValueError(
                f"robust_kernel: expected cauchy|huber|gnc|none, got {robust_kernel!r}"
            )
        for name, value in [
            ("kernel_scale", kernel_scale),
            ("seq_sigma_t", seq_sigma_t),
            ("seq_sigma_r", seq_sigma_r),
            ("loop_sigma_t", loop_sigma_t),
            ("loop_sigma_r", loop_sigma_r),
            ("max_iters", max_iters),
            ("rel_tol", rel_tol),
        ]:
            if not value > 0:
                raise ValueError(f"{name}: must be > 0, got {value}")
        self.robust_kernel = robust_kernel
        self.kernel_scale = float(kernel_scale)
        self.seq_sigma_t, self.seq_sigma_r = float(seq_sigma_t), float(seq_sigma_r)
        self.loop_sigma_t, self.loop_sigma_r = float(loop_sigma_t), float(loop_sigma_r)
        self.max_iters, self.rel_tol = int(max_iters), float(rel_tol)
        self.all_frames = bool(all_frames)
        # gtsam keys are the consecutive integers 0, 1, ... in insertion order; they double as
        # g2o vertex ids. A node name is (agent, "kf" | "frame", id).
        self._keys: dict[tuple[str, str, int], int] = {}
        self._names: list[tuple[str, str, int]] = []
        # Current estimate per node: the initial pose, then the last optimised one, so that a
        # re-run after a new loop starts from the corrected map.
        self._estimate: list[np.ndarray] = []
        self._initial: list[np.ndarray] = []  # as added, for `reset_estimate`
        self._edges: list[Edge] = []
        self._loop_ids: set[Hashable] = set()
        self._trajectories: dict[str, AgentTrajectory] = {}

    @classmethod
    def from_config(cls, cfg: PoseGraphConfig) -> PoseGraph:
        """A graph with the settings of the ``pose_graph`` config section (its fields are the
        constructor's arguments)."""
        return cls(**cfg.model_dump())

    # ---------------------------------------------------------------------------------------
    # building

    @property
    def num_nodes(self) -> int:
        return len(self._names)

    @property
    def num_edges(self) -> int:
        return len(self._edges)

    @property
    def loop_ids(self) -> list[Hashable]:
        return [e.loop_id for e in self._edges if e.loop_id is not None]

    def estimate(self, agent: str, kf_id: int) -> np.ndarray:
        """Current ``T_world_kf`` of a keyframe: optimised if ``optimize`` ran, else initial."""
        return self._estimate[self._key(agent, "kf", kf_id)].copy()

    def add_keyframe(self, agent: str, kf_id: int, T_world_kf_initial: np.ndarray) -> None:
        """Add a keyframe node with its initial pose in the group frame."""
        self._add_node((agent, "kf", int(kf_id)), T_world_kf_initial)

    def add_sequential(
        self,
        agent: str,
        kf_a: int,
        kf_b: int,
        T_a_b: np.ndarray,
        sigma_t: float | None = None,
        sigma_r: float | None = None,
    ) -> None:
        """Add a tracking edge: keyframe ``kf_b``'s pose in keyframe ``kf_a``'s frame."""
        info = _diag_information(
            self.seq_sigma_t if sigma_t is None else sigma_t,
            self.seq_sigma_r if sigma_r is None else sigma_r,
        )
        self._add_edge(self._key(agent, "kf", kf_a), self._key(agent, "kf", kf_b), T_a_b, info)

    def add_loop(
        self,
        agent_a: str,
        kf_a: int,
        agent_b: str,
        kf_b: int,
        T_a_b: np.ndarray,
        sigma_t: float | None = None,
        sigma_r: float | None = None,
        information: np.ndarray | None = None,
        loop_id: Hashable | None = None,
    ) -> Hashable:
        """Add a loop edge; returns its id (``loop_id`` or the next free integer).

        Its noise is ``information [6, 6]`` (translation first) if given, else diagonal from
        ``sigma_t``/``sigma_r`` (default: the graph's loop sigmas; see ``loop_sigmas`` for
        sigmas from registration quality).
        """
        if information is not None:
            if sigma_t is not None or sigma_r is not None:
                raise ValueError("add_loop: give either sigmas or an information matrix")
            info = np.asarray(information, dtype=np.float64)
            check_shape(info, (6, 6), "information")
            if not np.allclose(info, info.T) or np.linalg.eigvalsh(info).min() <= 0:
                raise ValueError("add_loop: information must be symmetric positive definite")
        else:
            info = _diag_information(
                self.loop_sigma_t if sigma_t is None else sigma_t,
                self.loop_sigma_r if sigma_r is None else sigma_r,
            )
        if loop_id is None:
            loop_id = len(self._loop_ids)
            while loop_id in self._loop_ids:
                loop_id += 1
        if loop_id in self._loop_ids:
            raise ValueError(f"add_loop: loop id {loop_id!r} already used")
        key_a, key_b = self._key(agent_a, "kf", kf_a), self._key(agent_b, "kf", kf_b)
        self._add_edge(key_a, key_b, T_a_b, info, loop_id)
        self._loop_ids.add(loop_id)
        return loop_id

    def add_trajectory(
        self, agent: str, traj: AgentTrajectory, T_group_world: np.ndarray | None = None
    ) -> None:
        """Add an agent's keyframes (and, in all-frames mode, frames) with sequential edges.

        ``T_group_world`` (default identity) maps the trajectory's world into the group frame,
        e.g. the alignment estimated at a merge; it changes initial values, not the edges.
        """
        if agent in self._trajectories:
            raise ValueError(f"add_trajectory: agent {agent!r} already added")
        T_g = np.eye(4) if T_group_world is None else np.asarray(T_group_world, np.float64)
        kf_ids = [int(k) for k in traj.kf_ids]
        kf_pose = dict(zip(kf_ids, compose(T_g, traj.T_world_kf), strict=True))
        if self.all_frames:
            chain = frame_chain(traj, kf_pose)
        else:
            kf_frames = [int(f) for f in traj.kf_frame_indices]
            chain = [(("kf", k), f, kf_pose[k]) for k, f in zip(kf_ids, kf_frames, strict=True)]
        for (kind, node_id), _, T_world_node in chain:
            self._add_node((agent, kind, node_id), T_world_node)
        for (name_a, frame_a, T_a), (name_b, frame_b, T_b) in pairwise(chain):
            # Tracking noise accumulates per frame: a random walk over n frames.
            root_n = np.sqrt(max(frame_b - frame_a, 1))
            info = _diag_information(self.seq_sigma_t * root_n, self.seq_sigma_r * root_n)
            self._add_edge(
                self._key(agent, *name_a),
                self._key(agent, *name_b),
                compose(invert(T_a), T_b),
                info,
            )
        self._trajectories[agent] = traj

    # ---------------------------------------------------------------------------------------
    # solving

    def optimize(self) -> PoseGraphResult:
        """Optimise all nodes; classify loops by their residual afterwards."""
        if not self._names:
            raise ValueError("optimize: the pose graph has no nodes")
        anchors = self._component_anchors()
        result, poses = solve(
            self._names,
            self._estimate,
            self._edges,
            anchors,
            robust_kernel=self.robust_kernel,
            kernel_scale=self.kernel_scale,
            max_iters=self.max_iters,
            rel_tol=self.rel_tol,
        )
        self._estimate = [T.copy() for T in poses]
        outliers = set(result.outlier_loops)
        loops = [e for e in self._edges if e.loop_id is not None]
        for edge in loops:
            if edge.loop_id in outliers:
                logger.info("pose graph: loop %s %s-%s disagrees with the rest (chi2 %.1f above "
                            "%.1f): %s", edge.loop_id, self._names[edge.key_a],
                            self._names[edge.key_b], result.loop_chi2[edge.loop_id],
                            CHI2_6DOF_95,
                            "rejected" if self.robust_kernel == "gnc" else "down-weighted")
        logger.info(
            "pose graph: %d nodes, %d edges, %d loops (%d outliers), error %.4g -> %.4g, "
            "%d components",
            self.num_nodes,
            self.num_edges,
            len(loops),
            len(result.outlier_loops),
            result.error_before,
            result.error_after,
            len(anchors),
        )
        return result

    def corrected_frames(self, result: PoseGraphResult, agent: str) -> np.ndarray:
        """Corrected ``T_world_frame [N, 4, 4]`` of the frames of an ``add_trajectory`` agent,
        in the order of its ``frame_indices``."""
        if agent not in self._trajectories:
            raise ValueError(f"corrected_frames: agent {agent!r} was not added by add_trajectory")
        traj = self._trajectories[agent]
        kf_poses = {k: T for (a, k), T in result.poses.items() if a == agent}
        out = correct_frames(kf_poses, traj.frame_kf_ids, traj.T_kf_frame)
        if self.all_frames:
            for i, frame in enumerate(np.asarray(traj.frame_indices).tolist()):
                if (agent, frame) in result.frame_poses:
                    out[i] = result.frame_poses[(agent, frame)]
        return out

    def reset_estimate(self) -> None:
        """Forget every optimisation: the next `optimize` starts from the initial poses again
        (to compare graphs that differ in their loops from the same start)."""
        self._estimate = [T.copy() for T in self._initial]

    def export_g2o(self, path: str | Path) -> None:
        """Write the graph (current estimate: optimised if ``optimize`` ran) as g2o SE3:QUAT."""
        names = [f"{a} {kind} {i}" for a, kind, i in self._names]
        edges = [(e.key_a, e.key_b, e.T_a_b, e.information) for e in self._edges]
        write_g2o(path, self._estimate, edges, fixed=self._component_anchors(), names=names)

    # ---------------------------------------------------------------------------------------
    # internals

    def _add_node(self, name: tuple[str, str, int], T_world_node: np.ndarray) -> None:
        agent = name[0]
        if not isinstance(agent, str) or not agent or any(c.isspace() for c in agent):
            raise ValueError(f"agent id must be a non-empty string without spaces, got {agent!r}")
        if name in self._keys:
            raise ValueError(f"node {name} already in the pose graph")
        T = np.asarray(T_world_node, dtype=np.float64)
        if T.shape != (4, 4) or not is_rigid(T):
            raise ValueError(f"node {name}: initial pose must be a rigid 4x4 matrix")
        self._keys[name] = len(self._names)
        self._names.append(name)
        self._estimate.append(T.copy())
        self._initial.append(T.copy())

    def _key(self, agent: str, kind: str, node_id: int) -> int:
        name = (agent, kind, int(node_id))
        if name not in self._keys:
            raise ValueError(f"no {kind} node {node_id} of agent {agent!r} in the pose graph")
        return self._keys[name]

    def _add_edge(
        self,
        key_a: int,
        key_b: int,
        T_a_b: np.ndarray,
        information: np.ndarray,
        loop_id: Hashable | None = None,
    ) -> None:
        T = np.asarray(T_a_b, dtype=np.float64)
        if T.shape != (4, 4) or not is_rigid(T):
            raise ValueError(
                f"edge {self._names[key_a]} -> {self._names[key_b]}: T_a_b must "
                "be a rigid 4x4 matrix"
            )
        if key_a == key_b:
            raise ValueError(f"edge from node {self._names[key_a]} to itself")
        self._edges.append(Edge(key_a, key_b, T.copy(), information, loop_id))

    def _component_anchors(self) -> list[int]:
        """The first-inserted node of each connected component (union-find over all edges)."""
        parent = list(range(self.num_nodes))

        def root(k: int) -> int:
            while parent[k] != k:
                parent[k] = parent[parent[k]]
                k = parent[k]
            return k

        for e in self._edges:
            ra, rb = root(e.key_a), root(e.key_b)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)  # the smaller key (inserted first) is root
        return sorted({root(k) for k in range(self.num_nodes)})


def _diag_information(sigma_t: float, sigma_r: float) -> np.ndarray:
    if not (sigma_t > 0 and sigma_r > 0):
        raise ValueError(f"sigmas must be > 0, got sigma_t={sigma_t}, sigma_r={sigma_r}")
    return np.diag([sigma_t**-2] * 3 + [sigma_r**-2] * 3)
