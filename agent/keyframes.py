"""Keyframes of one agent: pose, a small RGB-D copy, the full-size images (PNG-compressed,
for loop registration and relocalisation), the map points anchored to them, and
co-visibility by projected overlap.

Co-visibility needs 3-D points of each keyframe that move with its pose. The store keeps a
fixed, sparse set of them per keyframe (a regular subsample of its own small depth image,
back-projected into its camera frame), so `covisible` needs neither the map nor the images
and follows pose corrections (`set_pose`) for free. A keyframe's score for a query view is
the fraction of those points that land inside the query image in front of the camera: the
share of the keyframe that the view also sees.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from cpslam.common.camera import Intrinsics, resize_depth

logger = logging.getLogger(__name__)

__all__ = ["Keyframe", "KeyframeStore", "downsample_rgbd"]

FORMAT_VERSION = 1
# Back-projected depth samples kept per keyframe for co-visibility (a grid over the image).
_OVERLAP_GRID = (12, 16)
DEPTH_SCALE = 5000.0
"""Units per metre of the stored full-size depth (0.2 mm steps, up to 13.1 m)."""


@dataclass
class Keyframe:
    """One keyframe.

    Attributes:
        kf_id: id, unique within the agent (0, 1, 2, ... in creation order).
        frame_index: the sequence's frame index it was made from.
        timestamp: seconds.
        T_world_cam: [4, 4] float64 pose (corrected in place by `KeyframeStore.set_pose`).
        rgb_small: uint8 [h, w, 3], the frame downsampled by the store's factor.
        depth_small: float32 [h, w] metres, 0 = invalid.
        point_ids: int64 [M], ids of the map points anchored to this keyframe.
        xyz_cam: float32 [P, 3] sparse depth samples in this keyframe's camera frame
            (co-visibility).
        rgb_png, depth_png: the processed frame's colour and depth (uint16, 1/DEPTH_SCALE
            metres) as PNG bytes (uint8 [B]); `KeyframeStore.full_rgbd` decodes them.
    """

    kf_id: int
    frame_index: int
    timestamp: float
    T_world_cam: np.ndarray
    rgb_small: np.ndarray
    depth_small: np.ndarray
    point_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    xyz_cam: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.float32))
    rgb_png: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.uint8))
    depth_png: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.uint8))


class KeyframeStore:
    """The keyframes of one agent, in creation order.

    Args:
        intrinsics: intrinsics of the processed (full) frames.
        downscale: the stored RGB-D copies are this many times smaller per side.
    """

    def __init__(self, intrinsics: Intrinsics, downscale: int) -> None:
        if downscale < 1:
            raise ValueError(f"KeyframeStore: downscale must be >= 1, got {downscale}")
        self.intrinsics = intrinsics
        self.downscale = int(downscale)
        self.intrinsics_small = intrinsics.scaled(1.0 / downscale)
        self._frames: dict[int, Keyframe] = {}

    def __len__(self) -> int:
        return len(self._frames)

    def __iter__(self) -> Iterator[Keyframe]:
        return iter(self._frames.values())

    def __contains__(self, kf_id: int) -> bool:
        return int(kf_id) in self._frames

    def ids(self) -> list[int]:
        """Keyframe ids in creation order."""
        return list(self._frames)

    def get(self, kf_id: int) -> Keyframe:
        """The keyframe with this id (KeyError naming it when absent)."""
        try:
            return self._frames[int(kf_id)]
        except KeyError:
            raise KeyError(f"keyframe {kf_id} is not in the store (ids {self.ids()})") from None

    @property
    def latest(self) -> Keyframe | None:
        """The most recently added keyframe."""
        return next(reversed(self._frames.values()), None) if self._frames else None

    def next_id(self) -> int:
        """Id the next keyframe gets."""
        return max(self._frames, default=-1) + 1

    def add(
        self,
        frame_index: int,
        timestamp: float,
        T_world_cam: np.ndarray,
        rgb: np.ndarray,
        depth: np.ndarray,
    ) -> Keyframe:
        """Make a keyframe from a processed frame (full-size rgb uint8 [H, W, 3], depth
        float32 [H, W]); the store downsamples the copy. Returns it, with the next id."""
        if depth.shape != self.intrinsics.shape or rgb.shape != (*depth.shape, 3):
            raise ValueError(f"KeyframeStore.add: rgb {rgb.shape} / depth {depth.shape} do not "
                             f"match the intrinsics' {self.intrinsics.shape}")
        rgb_small, depth_small = downsample_rgbd(rgb, depth, self.intrinsics_small)
        kf = Keyframe(
            kf_id=self.next_id(),
            frame_index=int(frame_index),
            timestamp=float(timestamp),
            T_world_cam=np.array(T_world_cam, dtype=np.float64).reshape(4, 4),
            rgb_small=rgb_small,
            depth_small=depth_small,
            xyz_cam=_overlap_points(depth_small, self.intrinsics_small),
            rgb_png=_png(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)),
            depth_png=_png(_depth_units(depth)),
        )
        self._frames[kf.kf_id] = kf
        logger.debug("keyframe %d from frame %d (%d overlap points)", kf.kf_id, frame_index,
                     len(kf.xyz_cam))
        return kf

    def full_rgbd(self, kf_id: int) -> tuple[np.ndarray, np.ndarray]:
        """The keyframe's full-size rgb uint8 [H, W, 3] and depth float32 [H, W] (metres, to
        1/DEPTH_SCALE), decoded from the stored PNGs (intrinsics: `self.intrinsics`)."""
        kf = self.get(kf_id)
        if not len(kf.rgb_png) or not len(kf.depth_png):
            raise KeyError(f"keyframe {kf_id} has no full-size images (saved before they were "
                           "kept)")
        bgr = cv2.imdecode(kf.rgb_png, cv2.IMREAD_COLOR)
        units = cv2.imdecode(kf.depth_png, cv2.IMREAD_UNCHANGED)
        return (np.ascontiguousarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)),
                units.astype(np.float32) / DEPTH_SCALE)

    def set_pose(self, kf_id: int, T_world_cam: np.ndarray) -> None:
        """Correct a keyframe's pose (the map's pose table is the caller's to update)."""
        self.get(kf_id).T_world_cam = np.array(T_world_cam, dtype=np.float64).reshape(4, 4)

    def add_point_ids(self, kf_id: int, point_ids: np.ndarray | torch.Tensor) -> None:
        """Record map points newly anchored to a keyframe."""
        kf = self.get(kf_id)
        ids = np.asarray(torch.as_tensor(point_ids).cpu(), dtype=np.int64).reshape(-1)
        kf.point_ids = np.concatenate((kf.point_ids, ids))

    def overlap(self, T_world_cam: np.ndarray, intrinsics: Intrinsics) -> dict[int, float]:
        """Per keyframe id, the fraction of its overlap points inside the view T_world_cam."""
        T_cam_world = np.linalg.inv(np.asarray(T_world_cam, dtype=np.float64))
        scores = {}
        for kf in self._frames.values():
            if len(kf.xyz_cam) == 0:
                scores[kf.kf_id] = 0.0
                continue
            T_cam_kf = T_cam_world @ kf.T_world_cam
            xyz = kf.xyz_cam.astype(np.float64) @ T_cam_kf[:3, :3].T + T_cam_kf[:3, 3]
            z = xyz[:, 2]
            front = z > 1e-6
            zs = np.where(front, z, 1.0)
            u = intrinsics.fx * xyz[:, 0] / zs + intrinsics.cx
            v = intrinsics.fy * xyz[:, 1] / zs + intrinsics.cy
            inside = front & (u > -0.5) & (u < intrinsics.width - 0.5) \
                & (v > -0.5) & (v < intrinsics.height - 0.5)
            scores[kf.kf_id] = float(inside.mean())
        return scores

    def covisible(
        self,
        T_world_cam: np.ndarray,
        intrinsics: Intrinsics,
        k: int,
        exclude: tuple[int, ...] = (),
        min_overlap: float = 0.05,
    ) -> list[int]:
        """Ids of up to k keyframes that overlap most with the view (at least `min_overlap`
        of their points inside it), best first; ties go to the newer keyframe."""
        if k <= 0:
            return []
        scores = self.overlap(T_world_cam, intrinsics)
        ranked = sorted(
            (kf for kf, s in scores.items() if s >= min_overlap and kf not in exclude),
            key=lambda kf: (-scores[kf], -kf),
        )
        return ranked[:k]

    # ---------------------------------------------------------------------------- save/load

    def state_dict(self) -> dict:
        """Plain tensors and numbers (loadable with torch.load(weights_only=True))."""
        frames = list(self._frames.values())
        return {
            "format_version": FORMAT_VERSION,
            "downscale": self.downscale,
            "intrinsics": self.intrinsics.to_dict(),
            "keyframes": [
                {
                    "kf_id": kf.kf_id,
                    "frame_index": kf.frame_index,
                    "timestamp": kf.timestamp,
                    "T_world_cam": torch.from_numpy(kf.T_world_cam.copy()),
                    "rgb_small": torch.from_numpy(kf.rgb_small.copy()),
                    "depth_small": torch.from_numpy(kf.depth_small.copy()),
                    "point_ids": torch.from_numpy(kf.point_ids.copy()),
                    "xyz_cam": torch.from_numpy(kf.xyz_cam.copy()),
                    "rgb_png": torch.from_numpy(kf.rgb_png.copy()),
                    "depth_png": torch.from_numpy(kf.depth_png.copy()),
                }
                for kf in frames
            ],
        }

    def load_state_dict(self, state: dict, source: str = "keyframe state") -> None:
        """Replace the content by `state` (as written by `state_dict`)."""
        if int(state.get("format_version", -1)) != FORMAT_VERSION:
            raise ValueError(f"{source}: keyframe store format_version "
                             f"{state.get('format_version')}, expected {FORMAT_VERSION}")
        intrinsics = Intrinsics.from_dict(state["intrinsics"])
        if intrinsics != self.intrinsics:
            raise ValueError(f"{source}: keyframes were made at {intrinsics}, this store "
                             f"works at {self.intrinsics}")
        self.downscale = int(state["downscale"])
        self.intrinsics_small = self.intrinsics.scaled(1.0 / self.downscale)
        frames = {}
        for item in state["keyframes"]:
            kf = Keyframe(
                kf_id=int(item["kf_id"]),
                frame_index=int(item["frame_index"]),
                timestamp=float(item["timestamp"]),
                T_world_cam=item["T_world_cam"].cpu().numpy().astype(np.float64),
                rgb_small=item["rgb_small"].cpu().numpy().astype(np.uint8),
                depth_small=item["depth_small"].cpu().numpy().astype(np.float32),
                point_ids=item["point_ids"].cpu().numpy().astype(np.int64),
                xyz_cam=item["xyz_cam"].cpu().numpy().astype(np.float32),
                rgb_png=item["rgb_png"].cpu().numpy().astype(np.uint8) if "rgb_png" in item
                else np.zeros(0, np.uint8),
                depth_png=item["depth_png"].cpu().numpy().astype(np.uint8) if "depth_png" in item
                else np.zeros(0, np.uint8),
            )
            small = self.intrinsics_small.shape
            if kf.T_world_cam.shape != (4, 4) or kf.depth_small.shape != small:
                raise ValueError(f"{source}: keyframe {kf.kf_id} has pose "
                                 f"{kf.T_world_cam.shape} / depth {kf.depth_small.shape}, "
                                 f"expected (4, 4) / {small}")
            frames[kf.kf_id] = kf
        self._frames = frames


def downsample_rgbd(
    rgb: np.ndarray, depth: np.ndarray, small: Intrinsics
) -> tuple[np.ndarray, np.ndarray]:
    """Resize an RGB-D pair to `small`'s size: colour by area, depth by `resize_depth` (no
    mixing of depths across edges or with invalid zeros, sampled where the intrinsics say)."""
    size = (small.width, small.height)
    rgb_small = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    depth_small = resize_depth(depth, size)
    return np.ascontiguousarray(rgb_small), np.ascontiguousarray(depth_small, dtype=np.float32)


def _png(image: np.ndarray) -> np.ndarray:
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise ValueError("PNG encoding of a keyframe image failed")
    return data.reshape(-1)


def _depth_units(depth: np.ndarray) -> np.ndarray:
    """Depth in metres as uint16 units of 1/DEPTH_SCALE (0 where invalid or beyond range)."""
    units = np.round(np.nan_to_num(depth, nan=0.0) * DEPTH_SCALE)
    return np.where((units > 0) & (units < 65535), units, 0).astype(np.uint16)


def _overlap_points(depth: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """Back-projected depth on a regular pixel grid, float32 [P, 3] (valid pixels only)."""
    rows, cols = _OVERLAP_GRID
    v = np.linspace(0, intrinsics.height - 1, rows).round().astype(np.int64)
    u = np.linspace(0, intrinsics.width - 1, cols).round().astype(np.int64)
    vv, uu = np.meshgrid(v, u, indexing="ij")
    vv, uu = vv.ravel(), uu.ravel()
    z = depth[vv, uu].astype(np.float64)
    ok = np.isfinite(z) & (z > 0)
    vv, uu, z = vv[ok], uu[ok], z[ok]
    xyz = intrinsics.pixel_rays(uu, vv) * z[:, None]
    return xyz.astype(np.float32)
