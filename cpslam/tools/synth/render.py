"""Ray-cast RGB-D rendering of a synthetic scene, and a Kinect-like depth noise model.

Rays are built here, not with `RaycastingScene.create_rays_pinhole`, so that the pixel
convention is explicit: pixel (u, v) with integer coordinates at pixel centres, ray direction
R_world_cam @ [(u - cx) / fx, (v - cy) / fy, 1]. Because the camera-frame direction has z = 1,
the hit distance `t_hit` is the z-depth itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from cpslam.common.camera import Intrinsics
from cpslam.tools.synth.texture import shade

if TYPE_CHECKING:
    from cpslam.tools.synth.scene import Scene

# Kinect-like sensor limits (metres) and noise: sigma(z) = a + b (z - z0)^2.
MIN_RANGE = 0.3
MAX_RANGE = 6.0
_SIGMA_A, _SIGMA_B, _SIGMA_Z0 = 0.0012, 0.0019, 0.4


@dataclass
class RGBDImage:
    """One rendered view: RGB uint8 [H, W, 3], z-depth float32 metres [H, W] (0 = no hit),
    and the cosine between the viewing ray and the surface normal float32 [H, W]."""

    rgb: np.ndarray
    depth: np.ndarray
    cos_incidence: np.ndarray


def default_intrinsics(width: int, height: int) -> Intrinsics:
    """fx = fy = 0.8 width (about 64 degrees horizontal field of view), centred principal
    point (integer coordinates are pixel centres, so cx = (width - 1) / 2)."""
    f = 0.8 * width
    return Intrinsics(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)


class Renderer:
    """Renders colour and depth of a `Scene` through a pinhole camera.

    Args:
        scene: the synthetic scene (mesh with a material per triangle).
        intrinsics: the pinhole camera.
        threads: ray-casting threads (0 = all cores).
    """

    def __init__(self, scene: Scene, intrinsics: Intrinsics, threads: int = 0) -> None:
        import open3d as o3d  # lazy: keeps the CLI start fast

        self.scene = scene
        self.intrinsics = intrinsics
        self.threads = threads
        self._o3d = o3d
        self._raycast = o3d.t.geometry.RaycastingScene()
        self._raycast.add_triangles(
            o3d.core.Tensor(scene.vertices.astype(np.float32)),
            o3d.core.Tensor(scene.triangles.astype(np.uint32)),
        )
        k = intrinsics
        v, u = np.mgrid[0:k.height, 0:k.width].astype(np.float64)
        self._dirs_cam = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)],
                                  axis=-1).reshape(-1, 3)

    def render(self, T_world_cam: np.ndarray) -> RGBDImage:
        """Render the view of camera pose `T_world_cam` (4x4, OpenCV camera axes)."""
        T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
        if T_world_cam.shape != (4, 4):
            raise ValueError(f"render: T_world_cam must be 4x4, got {T_world_cam.shape}")
        k = self.intrinsics
        # einsum, not @: a BLAS call for this thin product is slower and oversubscribes cores.
        dirs_world = np.einsum("nk,jk->nj", self._dirs_cam, T_world_cam[:3, :3])
        rays = np.empty((len(dirs_world), 6), dtype=np.float32)
        rays[:, :3] = T_world_cam[:3, 3]
        rays[:, 3:] = dirs_world
        hits = self._raycast.cast_rays(self._o3d.core.Tensor(rays), nthreads=self.threads)
        t_hit = hits["t_hit"].numpy().astype(np.float64)
        prim = hits["primitive_ids"].numpy().astype(np.int64)
        normals = hits["primitive_normals"].numpy().astype(np.float64)
        valid = np.isfinite(t_hit)
        rgb = np.zeros((len(t_hit), 3))
        cos_inc = np.zeros(len(t_hit))
        if valid.any():
            t = t_hit[valid]
            d = dirs_world[valid]
            n = normals[valid]
            d_len = np.sqrt(np.einsum("ij,ij->i", d, d))
            cos_signed = np.einsum("ij,ij->i", n, d) / d_len
            n = n * -np.sign(cos_signed + 1e-12)[:, None]  # face the camera
            cos = np.abs(cos_signed)
            xyz = T_world_cam[:3, 3] + d * t[:, None]
            footprint = t / k.fx / np.maximum(cos, 0.2)
            mats = self.scene.material_ids[prim[valid]]
            rgb[valid] = shade(self.scene.materials, mats, xyz, n, footprint)
            cos_inc[valid] = cos
        depth = np.where(valid, t_hit, 0.0).astype(np.float32)
        return RGBDImage(
            rgb=np.round(rgb * 255.0).astype(np.uint8).reshape(k.height, k.width, 3),
            depth=depth.reshape(k.height, k.width),
            cos_incidence=cos_inc.astype(np.float32).reshape(k.height, k.width),
        )

    def distance(self, xyz: np.ndarray) -> np.ndarray:
        """Unsigned distance [N] from world points [N, 3] to the nearest scene surface."""
        query = self._o3d.core.Tensor(np.asarray(xyz, dtype=np.float32).reshape(-1, 3))
        return self._raycast.compute_distance(query, nthreads=self.threads).numpy().astype(
            np.float64)


def kinect_noise(depth: np.ndarray, cos_incidence: np.ndarray, rng: np.random.Generator,
                 dropout: float = 0.005) -> np.ndarray:
    """Corrupt clean z-depth like a structured-light sensor (Kinect v1 style).

    - axial noise with sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 metres;
    - no depth outside [MIN_RANGE, MAX_RANGE], at grazing angles (cos < 0.12) and, mostly,
      along depth discontinuities (the pixels on either side of a jump larger than 4 % of
      the depth, and some of their neighbours);
    - a small fraction `dropout` of pixels lost at random.

    Args:
        depth: [H, W] float32 clean z-depth in metres, 0 = no hit.
        cos_incidence: [H, W] cosine between viewing ray and surface normal.
        rng: the generator (seed it per frame for reproducible output).

    Returns:
        [H, W] float32 noisy depth, 0 = invalid.
    """
    z = depth.astype(np.float64)
    valid = z > 0
    padded = np.pad(z, 1, mode="edge")
    jump = np.zeros_like(z)
    for dv, du in ((0, 1), (2, 1), (1, 0), (1, 2)):
        neighbour = padded[dv:dv + z.shape[0], du:du + z.shape[1]]
        jump = np.maximum(jump, np.abs(neighbour - z))
    edge = valid & (jump > 0.04 * np.maximum(z, 0.5))
    near_edge = np.zeros_like(edge)
    near_edge[1:, :] |= edge[:-1, :]
    near_edge[:-1, :] |= edge[1:, :]
    near_edge[:, 1:] |= edge[:, :-1]
    near_edge[:, :-1] |= edge[:, 1:]
    lost = (edge & (rng.random(z.shape) < 0.85)) | (near_edge & (rng.random(z.shape) < 0.3))
    lost |= rng.random(z.shape) < dropout
    lost |= cos_incidence < 0.12
    sigma = _SIGMA_A + _SIGMA_B * (z - _SIGMA_Z0) ** 2
    noisy = z + sigma * rng.standard_normal(z.shape)
    keep = valid & ~lost & (z >= MIN_RANGE) & (z <= MAX_RANGE)
    return np.where(keep, noisy, 0.0).astype(np.float32)
