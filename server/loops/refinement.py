"""Rendering-based refinement of a loop's relative pose: the loop keyframe tracked against the
other agent's sub-map (the paper's relative pose estimation), after the coarse registration.

A loop candidate pairs the query keyframe a (agent A) with a stored keyframe b (agent B); the
coarse registration gives ``T_a_b`` (b's camera frame into a's). The refiner

1. builds B's sub-map as the server holds it (`Registry`: points anchored to B's keyframes at
   their reported poses in B's own world, B's latest decoder weights). For a loop within one
   agent only the points anchored to keyframes nearer (in keyframe order) to b than to a are
   kept: the others were mapped from a's drifted poses and would pull a back onto its own
   odometry;
2. places camera a in B's world at ``T_B_a = T_B_b @ inv(T_a_b)`` and tracks a's depth
   against the sub-map (`cpslam.common.field.tracking.Tracker`, the agent's tracker: depth L1
   with the outlier mask, ``loop.register_iters`` Adam steps, best-loss pose kept);
3. recomputes the geometric verification of the registration for both poses
   (`cpslam.common.registration.verify` on the two keyframes: overlap, RMS point-to-plane
   residual, free space, colour) and the tracking loss against the sub-map on pixels drawn
   afresh (not the batch the tracker minimised). The refined pose is used when it passes the
   verification and neither its residual nor its loss is worse than the coarse pose's;
   otherwise the coarse pose is kept, and the result says so.

Why the residual between the two keyframes decides, and not the fit to the sub-map alone: the
sub-map carries B's drift between keyframe b and the keyframes its points are anchored to, and
the fit of a neural map is good to a few millimetres at best. Tracking against it always lowers
the loss against the map (measured on every loop of the synthetic runs, docs/loops.md), also
where it moves the pose away from the truth; the loop edge relates a to b, and the two
keyframes' own depth is what says whether the pose between them got better.

The result is a `Registration` whose overlap and residual belong to the pose it carries, so the
back end's thresholds apply unchanged; ``method`` is "render" (refined) or "coarse" (kept), and
``details["refinement"]`` holds plain numbers for metrics.json (coarse pose, residuals, steps,
how far the pose moved, time, reason). Nothing here raises into the back end: a refinement
that cannot run (no decoder weights or points of B yet, an internal error) returns None and
the back end keeps the coarse registration.
"""

from __future__ import annotations

import logging
import math
import time
import zlib
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from cpslam.common.camera import Intrinsics
from cpslam.common.field import Decoders, FieldSpec, NeuralPointMap
from cpslam.common.field.tracking import Tracker
from cpslam.common.geometry import compose, invert
from cpslam.common.registration import Registration, RegistrationParams, verify
from cpslam.server.loops.registration import keyframe_rgbd

if TYPE_CHECKING:
    from collections.abc import Callable

    from cpslam.common.config import CpslamConfig
    from cpslam.protocol import KeyframeImage
    from cpslam.server.registry import Registry

__all__ = ["PoseRefiner"]

logger = logging.getLogger(__name__)


class PoseRefiner:
    """Refines loop relative poses by tracking against the other sub-map (module docstring).

    Use it as the back end's ``refine_pose`` hook: ``refiner(candidate, T_a_b, image_a,
    image_b)``; `refine` does the work for an explicit map and decoders.

    Args:
        registry: the server's registry (read at every call: B's points, keyframes, weights).
        spec: the agents' field (sub-map, decoders of their shape, tracker's rendering).
        params: thresholds of the geometric verification (the ``loop`` section).
        seed: seeds the pixel draws (with the pair, so a pair refines the same way each time).
        **tracker_args: keyword arguments of `Tracker` (the ``tracking`` section,
            `tracker_args_from_config`; ``iters`` is ``loop.register_iters``); ``n_pixels``
            pixels are drawn for tracking and again for the residual check.
    """

    def __init__(
        self,
        registry: Registry | None,
        spec: FieldSpec,
        *,
        params: RegistrationParams,
        seed: int,
        **tracker_args: Any,
    ) -> None:
        self.registry = registry
        self.spec = spec
        self.tracker_args: dict[str, Any] = dict(tracker_args)
        Tracker(Intrinsics(1.0, 1.0, 0.0, 0.0, 1, 1), spec, **self.tracker_args)  # checks
        self.params = params
        self.seed = int(seed)

    @classmethod
    def from_config(cls, cfg: CpslamConfig, registry: Registry | None) -> PoseRefiner:
        """Settings of the ``field``, ``tracking`` and ``loop`` sections."""
        from cpslam.common.field_config import field_spec, tracker_args_from_config

        lp = cfg.loop
        return cls(
            registry, field_spec(cfg.field),
            params=RegistrationParams.from_config(lp, cfg.run.seed), seed=cfg.run.seed,
            **{**tracker_args_from_config(cfg.tracking), "iters": lp.register_iters})

    # ------------------------------------------------------------------------------ hook

    def __call__(self, cand: Any, T_a_b: np.ndarray, img_a: KeyframeImage,
                 img_b: KeyframeImage) -> Registration | None:
        """The back end's ``refine_pose``: refined (or kept) registration, None when the
        refinement cannot run (the back end then keeps its coarse registration)."""
        return self.bind(cand)(T_a_b, img_a, img_b)

    def bind(self, cand: Any) -> Callable[[np.ndarray, KeyframeImage, KeyframeImage],
                                          Registration | None]:
        """``(T_a_b, image_a, image_b) -> Registration | None`` for `cand`, with B's sub-map and
        decoders read now (copies): the loop verification worker refines on its own thread
        while the registry goes on taking messages."""
        pair = f"{cand.agent_a}/{cand.kf_a} - {cand.agent_b}/{cand.kf_b}"
        try:
            got = self.submap(cand)
        except Exception:  # noqa: BLE001 - a failing refinement must not reject the loop
            logger.exception("loop %s: reading the sub-map to refine against failed", pair)
            got = "sub-map unreadable"
        seed = zlib.crc32(f"{self.seed}:{cand.agent_a}:{cand.kf_a}:{cand.agent_b}:"
                          f"{cand.kf_b}".encode())

        def refine(T_a_b: np.ndarray, img_a: KeyframeImage,
                   img_b: KeyframeImage) -> Registration | None:
            if isinstance(got, str):
                logger.info("loop %s: not refined (%s)", pair, got)
                return None
            point_map, decoders, T_B_b = got
            try:
                return self.refine(point_map, decoders, T_B_b, T_a_b, img_a, img_b, seed)
            except Exception:  # noqa: BLE001 - a failing refinement must not reject the loop
                logger.exception("refinement of loop %s failed; coarse pose kept", pair)
                return None

        return refine

    def submap(self, cand: Any) -> tuple[NeuralPointMap, Decoders, np.ndarray] | str:
        """B's sub-map in B's own world, B's decoders and ``T_B_b``; or why there are none."""
        if self.registry is None or cand.agent_b not in self.registry.agents:
            return f"agent {cand.agent_b} unknown"
        rec = self.registry.agents[cand.agent_b]
        if int(cand.kf_b) not in rec.keyframes:
            return f"keyframe {cand.agent_b}/{cand.kf_b} unknown"
        if rec.decoder is None:
            return f"no decoder weights from agent {cand.agent_b} yet"
        point_map = rec.submap(self.spec.feature_dim, self.spec.grid_size)
        if cand.agent_a == cand.agent_b:  # keep the points mapped nearer to b than to a
            kfs = np.asarray(rec.kf_ids)
            i_a, i_b = np.searchsorted(kfs, [int(cand.kf_a), int(cand.kf_b)])
            rank = np.searchsorted(kfs, point_map.anchor_kf.cpu().numpy())
            point_map = point_map.subset(torch.from_numpy(np.abs(rank - i_b) < np.abs(rank - i_a)))
        if len(point_map) == 0:
            return f"no points of agent {cand.agent_b} to track against"
        decoders = self.spec.decoders(self.seed)
        decoders.load_state_dict({k: torch.as_tensor(v) for k, v in rec.decoder.items()})
        decoders.eval()
        return point_map, decoders, np.array(rec.keyframes[int(cand.kf_b)].T_own_kf)

    # ------------------------------------------------------------------------------ work

    def refine(self, point_map: NeuralPointMap, decoders: Decoders, T_B_b: np.ndarray,
               T_a_b: np.ndarray, img_a: KeyframeImage, img_b: KeyframeImage,
               seed: int = 0) -> Registration:
        """Refine ``T_a_b`` by tracking a's depth against ``point_map`` (B's world, in which
        keyframe b sits at ``T_B_b``), then keep the better of coarse and refined."""
        t0 = time.perf_counter()
        T_a_b = np.asarray(T_a_b, np.float64)
        intr_a, intr_b = Intrinsics.of(img_a), Intrinsics.of(img_b)
        rgb_a, depth_a = keyframe_rgbd(img_a)
        depth_t = torch.from_numpy(depth_a).to(point_map.device)
        rgb_t = torch.from_numpy(rgb_a).to(point_map.device).float() / 255.0
        tracker = Tracker(intr_a, self.spec, **self.tracker_args)
        T_B_a0 = compose(T_B_b, invert(T_a_b))
        track = tracker.track(point_map, decoders, rgb_t, depth_t, T_B_a0,
                              torch.Generator().manual_seed(seed))
        T_a_b_ref = compose(invert(track.T_world_cam), T_B_b)
        # The residual on fresh pixels: the tracked batch always favours the refined pose.
        check = Tracker(intr_a, self.spec, **{**self.tracker_args, "iters": 1})
        losses = []
        for T in (T_B_a0, track.T_world_cam):
            out = check.track(point_map, decoders, rgb_t, depth_t, T,
                              torch.Generator().manual_seed(seed + 1))
            losses.append(out.losses[0] if out.losses else math.inf)
        loss_coarse, loss_refined = losses
        src, dst = keyframe_rgbd(img_b), (rgb_a, depth_a)
        refined = verify(src, dst, intr_b, T_a_b_ref, self.params, dst_intrinsics=intr_a)
        coarse = verify(src, dst, intr_b, T_a_b, self.params, dst_intrinsics=intr_a)
        if not refined.success:
            note = f"refined pose failed verification ({refined.reason}): coarse kept"
        elif refined.inlier_rmse > coarse.inlier_rmse:
            note = (f"refined residual {refined.inlier_rmse:.4f} m > coarse "
                    f"{coarse.inlier_rmse:.4f} m: coarse kept")
        elif loss_refined > loss_coarse:
            note = (f"refined depth error against the sub-map {loss_refined:.4f} m > coarse "
                    f"{loss_coarse:.4f} m: coarse kept")
        else:
            note = "refined"
        used = note == "refined"
        result = refined if used else coarse
        moved = compose(invert(T_a_b), T_a_b_ref)
        result.method = "render" if used else "coarse"
        result.seconds = time.perf_counter() - t0
        result.details["refinement"] = {
            "used": used, "note": note, "T_coarse": T_a_b.tolist(),
            "T_refined": T_a_b_ref.tolist(), "rmse_coarse": float(coarse.inlier_rmse),
            "rmse_refined": float(refined.inlier_rmse), "fitness_coarse": float(coarse.fitness),
            "fitness_refined": float(refined.fitness), "loss_coarse": float(loss_coarse),
            "loss_refined": float(loss_refined), "iters": int(track.iters),
            "best_iter": int(track.best_iter), "points": len(point_map),
            "moved_m": float(np.linalg.norm(moved[:3, 3])),
            "moved_deg": float(np.degrees(np.arccos(np.clip((np.trace(moved[:3, :3]) - 1) / 2,
                                                            -1.0, 1.0)))),
            "seconds": float(result.seconds)}
        logger.info("loop refinement: %s (moved %.1f mm, %.2f deg; residual %.4f -> %.4f m; "
                    "%.2f s)", note, 1e3 * result.details["refinement"]["moved_m"],
                    result.details["refinement"]["moved_deg"], loss_coarse, loss_refined,
                    result.seconds)
        return result
