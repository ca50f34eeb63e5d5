"""Tracking failure detection and recovery.

Tracking against the map can go wrong: a guess a degree off on striped texture, a frame that
mostly sees unmapped space, a fast turn. Left alone, a wrong pose is mapped, the map bends
to it and every later frame follows. Each tracked frame is therefore checked (`check`):

- residual jump: the median depth error of the pixels reaching the map is more than
  `residual_jump` times the median of the last `window` healthy frames;
- few inliers: the tracking loss kept less than `min_inliers` of the frame's pixels;
- implausible motion: the pose is more than `max_jump_t` metres or `max_jump_r` radians
  from the motion model's prediction (a hand-held camera at 30 Hz does not jump).

A suspect frame is tracked again (`Recovery.recover`) from each other guess, with
`iters_factor` times the steps and the loss tracking has (the keyframe reference terms
included): the previous pose (zero motion), the constant-velocity prediction, and a
frame-to-frame RGB-D odometry estimate from the previous frame (Open3D's multi-scale hybrid
odometry, when open3d is installed). Every result, the first included, is
scored on one common set of pixels (`Tracker.score`) and the best is kept. If it is still
suspect, the frame is registered against the latest keyframes (`register_rgbd` on their
full-size images) and tracked from each pose that verifies. A frame that is still suspect is
"lost": it keeps the best pose found, and the odometry neither maps it nor makes it a
keyframe. Every event is logged and counted.
"""

from __future__ import annotations

import importlib.util
import logging
from collections import Counter, deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from cpslam.common.geometry import invert, se3_log

if TYPE_CHECKING:
    from collections.abc import Sequence

    from cpslam.agent.keyframes import KeyframeStore
    from cpslam.common.camera import Intrinsics
    from cpslam.common.config import RecoveryConfig
    from cpslam.common.field import Decoders, NeuralPointMap
    from cpslam.common.field.image_terms import ReferenceImage
    from cpslam.common.field.tracking import Tracker, TrackResult

logger = logging.getLogger(__name__)

__all__ = ["Frame", "Recovery", "RecoveryOutcome"]


@dataclass(frozen=True)
class Frame:
    """One frame as the recovery needs it: uint8 rgb [H, W, 3] and float32 depth [H, W] (m,
    0 = invalid) in numpy, the same as tensors on the map's device (rgb float in [0, 1])."""

    index: int
    rgb: np.ndarray
    depth: np.ndarray
    rgb_t: torch.Tensor
    depth_t: torch.Tensor

    @classmethod
    def from_arrays(cls, index: int, rgb: np.ndarray, depth: np.ndarray,
                    device: torch.device | str) -> Frame:
        """The frame of uint8 rgb [H, W, 3] and float32 depth [H, W], with its tensors."""
        return cls(int(index), rgb, depth, torch.from_numpy(rgb).to(device).float() / 255.0,
                   torch.from_numpy(depth).to(device))


@dataclass
class RecoveryOutcome:
    """The pose to use and what happened: event "" (healthy), "recovered" or "lost"; how:
    the guess that won ("tracked", "zero_motion", "constant_velocity", "rgbd_odometry",
    "keyframe <id>"); reason: why the frame was suspect."""

    result: TrackResult
    event: str = ""
    how: str = "tracked"
    reason: str = ""


class Recovery:
    """Checks tracked frames and recovers suspect ones (see the module docstring).

    Args: the fields of the `recovery` config section; `iters` is tracking's step count.
    """

    def __init__(
        self,
        *,
        residual_jump: float,
        min_inliers: float,
        max_jump_t: float,
        max_jump_r: float,
        window: int,
        iters_factor: float,
        geometric_guess: bool,
        relocalise: bool,
        iters: int,
    ) -> None:
        self.residual_jump, self.min_inliers = residual_jump, min_inliers
        self.max_jump_t, self.max_jump_r = max_jump_t, max_jump_r
        self.retrack_iters = max(1, round(iters_factor * iters))
        self.geometric_guess, self.relocalise = geometric_guess, relocalise
        self._residuals: deque[float] = deque(maxlen=window)
        self.counts: Counter[str] = Counter()

    @classmethod
    def from_config(cls, cfg: RecoveryConfig, tracking_iters: int) -> Recovery:
        """The `recovery` section's checks; re-tracking runs iters_factor x tracking_iters."""
        fields = cfg.model_dump(exclude={"enabled"})
        return cls(**fields, iters=tracking_iters)

    def state_dict(self) -> dict:
        """The recent healthy frames' depth errors and the event counts (to resume a run)."""
        return {"residuals": [float(r) for r in self._residuals],
                "counts": {k: int(v) for k, v in self.counts.items()}}

    def load_state_dict(self, state: dict) -> None:
        self._residuals.clear()
        self._residuals.extend(float(r) for r in state.get("residuals", []))
        self.counts = Counter({str(k): int(v) for k, v in state.get("counts", {}).items()})

    # ---------------------------------------------------------------------------- checks

    def check(self, result: TrackResult, T_predicted: np.ndarray) -> str:
        """Why the tracked result is suspect ("" when it looks healthy)."""
        if not np.all(np.isfinite(result.T_world_cam)):
            return "pose not finite"
        if self._residuals and result.residual_m > self.residual_jump * float(
                np.median(self._residuals)):
            return (f"depth error {1000 * result.residual_m:.1f} mm, "
                    f"{result.residual_m / float(np.median(self._residuals)):.1f}x the recent")
        if result.inlier_ratio < self.min_inliers:
            return f"{100 * result.inlier_ratio:.0f} % of the pixels kept"
        dt, dr = _distance(T_predicted, result.T_world_cam)
        if dt > self.max_jump_t or dr > self.max_jump_r:
            return f"{100 * dt:.1f} cm / {np.degrees(dr):.1f} deg from the motion model"
        return ""

    def accept(self, result: TrackResult) -> None:
        """Record a healthy frame's depth error (the reference of the residual check)."""
        if np.isfinite(result.residual_m):
            self._residuals.append(float(result.residual_m))

    # ---------------------------------------------------------------------------- recovery

    def recover(
        self,
        tracker: Tracker,
        point_map: NeuralPointMap,
        decoders: Decoders,
        frame: Frame,
        first: TrackResult,
        reason: str,
        guesses: dict[str, np.ndarray],
        previous: Frame | None,
        T_previous: np.ndarray | None,
        intrinsics: Intrinsics,
        keyframes: KeyframeStore | None,
        generator_seed: int,
        reference: Sequence[ReferenceImage] = (),
    ) -> RecoveryOutcome:
        """Re-track a suspect frame from other guesses (``guesses``: name -> T_world_cam,
        the one it was tracked from included), then from keyframes; the best outcome. Every
        re-track has the loss the frame was tracked with (``reference``: the keyframe view
        tracking compared it with, if any)."""
        self.counts["suspect"] += 1
        guesses = dict(guesses)
        if self.geometric_guess and previous is not None and T_previous is not None:
            T_prev_cur = rgbd_odometry(previous, frame, intrinsics)
            if T_prev_cur is not None:
                guesses["rgbd_odometry"] = T_previous @ T_prev_cur
        T_predicted = guesses.get("constant_velocity", guesses.get("zero_motion"))
        candidates = [("tracked", first)] + self._track_all(
            tracker, point_map, decoders, frame, guesses, generator_seed, reference)
        best_name, best = self._best(tracker, point_map, decoders, frame, candidates,
                                     generator_seed)
        healthy = not self._still_suspect(best, T_predicted, guesses.get("rgbd_odometry"))
        if not healthy and self.relocalise and keyframes is not None and len(keyframes):
            relocated = self._track_all(tracker, point_map, decoders, frame,
                                        _keyframe_guesses(frame, keyframes, intrinsics),
                                        generator_seed, reference)
            if relocated:
                best_name, best = self._best(tracker, point_map, decoders, frame,
                                             [(best_name, best), *relocated], generator_seed)
                healthy = not self._still_suspect(best, None, None)
        event = "recovered" if healthy else "lost"
        self.counts[event] += 1
        if healthy:
            self.accept(best)
            logger.info("frame %d: tracking suspect (%s); recovered from %s", frame.index,
                        reason, best_name)
        else:
            logger.warning("frame %d: tracking lost (%s); kept the best guess (%s), not "
                           "mapped", frame.index, reason, best_name)
        return RecoveryOutcome(best, event, best_name, reason)

    def _track_all(self, tracker: Tracker, point_map: NeuralPointMap, decoders: Decoders,
                   frame: Frame, guesses: dict[str, np.ndarray], seed: int,
                   reference: Sequence[ReferenceImage]) -> list[tuple[str, TrackResult]]:
        out = []
        for name, T in guesses.items():
            gen = torch.Generator(device="cpu").manual_seed(seed)
            out.append((name, tracker.track(point_map, decoders, frame.rgb_t, frame.depth_t, T,
                                            gen, iters=self.retrack_iters,
                                            reference=reference)))
        return out

    @staticmethod
    def _best(tracker: Tracker, point_map: NeuralPointMap, decoders: Decoders, frame: Frame,
              candidates: list[tuple[str, TrackResult]], seed: int
              ) -> tuple[str, TrackResult]:
        # One extra draw (seed + 1) scores every candidate on pixels none was tracked on.
        gen = torch.Generator(device="cpu").manual_seed(seed + 1)
        scores = tracker.score(point_map, decoders, frame.rgb_t, frame.depth_t,
                               [r.T_world_cam for _, r in candidates], gen)
        return candidates[int(np.argmin(scores))]

    def _still_suspect(self, result: TrackResult, T_predicted: np.ndarray | None,
                       T_odometry: np.ndarray | None) -> bool:
        """A recovered pose passes the residual and inlier checks and agrees with the motion
        model or with the frame-to-frame odometry (a real sudden move agrees with the
        latter); without either prediction, only the first two are checked."""
        references = [T for T in (T_predicted, T_odometry) if T is not None]
        checks = [self.check(result, T) for T in references] or [self.check(result, np.asarray(
            result.T_world_cam))]
        return all(checks)


def rgbd_odometry(previous: Frame, frame: Frame, intrinsics: Intrinsics) -> np.ndarray | None:
    """T_previous_current [4, 4] by Open3D's multi-scale hybrid RGB-D odometry, or None (no
    open3d, or no convergence)."""
    try:
        import open3d as o3d
    except ImportError:
        return None
    images = [open3d_rgbd(f.rgb, f.depth, float(max(f.depth.max(), 1e-3)) + 1.0)
              for f in (frame, previous)]
    ok, T_prev_cur, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
        images[0], images[1], open3d_pinhole(intrinsics), np.eye(4),
        o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm(),
        o3d.pipelines.odometry.OdometryOption())
    return np.asarray(T_prev_cur, dtype=np.float64) if ok else None


def open3d_pinhole(intrinsics: Intrinsics):
    """The intrinsics as Open3D's `PinholeCameraIntrinsic` (open3d must be importable)."""
    import open3d as o3d

    return o3d.camera.PinholeCameraIntrinsic(intrinsics.width, intrinsics.height,
                                             intrinsics.fx, intrinsics.fy,
                                             intrinsics.cx, intrinsics.cy)


def open3d_rgbd(rgb: np.ndarray, depth: np.ndarray, depth_trunc: float):
    """rgb [H, W, 3] uint8 and depth [H, W] metres as Open3D's `RGBDImage`, with intensity
    for the odometry's photometric term (open3d must be importable)."""
    import open3d as o3d

    return o3d.geometry.RGBDImage.create_from_color_and_depth(
        o3d.geometry.Image(np.ascontiguousarray(rgb)),
        o3d.geometry.Image(np.ascontiguousarray(depth)), depth_scale=1.0,
        depth_trunc=depth_trunc, convert_rgb_to_intensity=True)


def _keyframe_guesses(frame: Frame, keyframes: KeyframeStore, intrinsics: Intrinsics,
                      latest: int = 3) -> dict[str, np.ndarray]:
    """Poses of the frame from registering it against the latest keyframes' full-size images
    (those that verify); none without open3d, which the registration needs (an optional
    guess, as Open3D's odometry in `rgbd_odometry`)."""
    if importlib.util.find_spec("open3d") is None:
        return {}
    from cpslam.common.registration import register_rgbd

    guesses = {}
    for kf_id in keyframes.ids()[-latest:]:
        try:
            rgb, depth = keyframes.full_rgbd(kf_id)
        except KeyError:  # saved before full-size images were kept
            continue
        reg = register_rgbd((frame.rgb, frame.depth), (rgb, depth), intrinsics)
        if reg.success:
            guesses[f"keyframe {kf_id}"] = keyframes.get(kf_id).T_world_cam @ reg.T_dst_src
    return guesses


def _distance(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (rad) between two poses."""
    xi = se3_log(invert(T_a) @ T_b)
    return float(np.linalg.norm(T_b[:3, 3] - T_a[:3, 3])), float(np.linalg.norm(xi[3:]))
