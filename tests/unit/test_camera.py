"""Pinhole intrinsics: validation, projection round trips, resizing conventions, torch helpers."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from cpslam.common.camera import (
    Intrinsics,
    backproject_torch,
    depth_noise,
    pixel_rays_torch,
    resize_rgbd,
    scaled_size,
)

INTR = Intrinsics(fx=525.0, fy=520.0, cx=319.5, cy=239.5, width=640, height=480)


def small_intr() -> Intrinsics:
    return Intrinsics(fx=50.0, fy=55.0, cx=31.2, cy=22.7, width=64, height=48)


@pytest.mark.parametrize(
    "field, value",
    [
        ("fx", 0.0),
        ("fy", -1.0),
        ("cx", float("nan")),
        ("cy", "abc"),
        ("width", 0),
        ("height", 1.5),
        ("width", True),
        ("height", "x"),
    ],
)
def test_validation_names_the_field(field: str, value: object) -> None:
    args = {"fx": 500.0, "fy": 500.0, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480}
    args[field] = value
    with pytest.raises(ValueError, match=f"Intrinsics.{field}"):
        Intrinsics(**args)


def test_coercion_and_dict_round_trips() -> None:
    intr = Intrinsics(np.float32(500), 500, 320, 240, np.int64(640), 480.0)
    assert isinstance(intr.fx, float) and isinstance(intr.width, int) and intr.height == 480
    assert Intrinsics.from_dict(INTR.to_dict()) == INTR
    sidecar = {**INTR.to_dict(), "depth_scale": 6553.5, "fps": 30}
    assert Intrinsics.from_dict(sidecar) == INTR
    with pytest.raises(ValueError, match="missing key.*cy"):
        Intrinsics.from_dict({"fx": 1, "fy": 1, "cx": 1, "width": 2, "height": 2})
    assert Intrinsics.from_K(INTR.K, 640, 480) == INTR
    np.testing.assert_array_equal(INTR.K, [[525, 0, 319.5], [0, 520, 239.5], [0, 0, 1]])
    with pytest.raises(ValueError, match="from_K"):
        Intrinsics.from_K(np.ones((3, 3)), 640, 480)
    assert INTR.shape == (480, 640)


def test_of_reads_any_camera_carrier_and_checks_it() -> None:
    message = SimpleNamespace(**INTR.to_dict(), kf_id=3, rgb=None)
    assert Intrinsics.of(message) == INTR
    with pytest.raises(ValueError, match="Intrinsics.fy"):
        Intrinsics.of(SimpleNamespace(**{**INTR.to_dict(), "fy": 0.0}))


def test_backproject_project_identity() -> None:
    intr = small_intr()
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.3, 5.0, size=intr.shape).astype(np.float32)
    xyz = intr.backproject(depth)
    assert xyz.shape == (48, 64, 3) and xyz.dtype == np.float32
    np.testing.assert_array_equal(xyz[..., 2], depth)
    uv, z = intr.project(xyz.reshape(-1, 3))
    u, v = intr.pixel_grid()
    np.testing.assert_allclose(uv[:, 0], u.reshape(-1), atol=1e-3)
    np.testing.assert_allclose(uv[:, 1], v.reshape(-1), atol=1e-3)
    np.testing.assert_allclose(z, depth.reshape(-1), rtol=1e-6)
    # the same points via z = 1 rays scaled by depth
    rays = intr.pixel_rays(u, v)
    np.testing.assert_allclose(rays[:, 2], 1.0)
    np.testing.assert_allclose(
        rays * depth.reshape(-1, 1), xyz.reshape(-1, 3), rtol=1e-5, atol=1e-6
    )


def test_backproject_invalid_depth_and_shape() -> None:
    intr = small_intr()
    depth = np.zeros(intr.shape, np.float32)
    depth[3, 5] = 2.0
    xyz = intr.backproject(depth)
    assert np.count_nonzero(np.any(xyz != 0, axis=-1)) == 1
    np.testing.assert_allclose(
        xyz[3, 5], [(5 - 31.2) * 2 / 50, (3 - 22.7) * 2 / 55, 2.0], rtol=1e-6
    )
    with pytest.raises(ValueError, match=r"\(48, 64\)"):
        intr.backproject(np.zeros((64, 48), np.float32))


def test_project_behind_camera_is_nan() -> None:
    uv, z = INTR.project(np.array([[0.0, 0.0, 1.0], [0.1, 0.0, -1.0], [0.0, 0.0, 0.0]]))
    np.testing.assert_allclose(uv[0], [319.5, 239.5])
    assert np.isnan(uv[1:]).all()
    np.testing.assert_array_equal(z, [1.0, -1.0, 0.0])
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        INTR.project(np.zeros(3))


def test_scaled_maps_pixel_centres() -> None:
    half = INTR.scaled(0.5)
    assert (half.width, half.height) == (320, 240)
    assert (half.fx, half.fy) == (262.5, 260.0)
    # centre of the image stays the centre; image borders (-0.5, W - 0.5) stay borders
    assert (half.cx, half.cy) == (159.5, 119.5)
    off = Intrinsics(500.0, 500.0, -0.5, 479.5, 640, 480).scaled(0.25)
    assert (off.cx, off.cy) == (-0.5, 119.5)
    # a 3-D point lands on continuous coordinate x in the original and (x + 0.5) s - 0.5 after
    xyz = np.array([[0.3, -0.2, 2.0], [-1.0, 0.7, 3.5]])
    uv, _ = INTR.scaled(1.0).project(xyz)
    for s in (0.5, 0.25, 2.0):
        uv_s, _ = INTR.scaled(s).project(xyz)
        np.testing.assert_allclose(uv_s, (uv + 0.5) * s - 0.5, atol=1e-9)
    with pytest.raises(ValueError, match="positive"):
        INTR.scaled(0.0)


@pytest.mark.parametrize("factor, interp", [(0.5, cv2.INTER_AREA), (2.0, cv2.INTER_LINEAR)])
def test_scaled_agrees_with_opencv_resize(factor: float, interp: int) -> None:
    """Resize images whose values are the original u and v coordinates; the scaled intrinsics
    must send each new pixel's ray to the original coordinate OpenCV sampled there."""
    intr = small_intr()
    u, v = intr.pixel_grid()
    size = scaled_size(intr.width, intr.height, factor)
    u_new = cv2.resize(u, size, interpolation=interp)
    v_new = cv2.resize(v, size, interpolation=interp)
    new = intr.scaled(factor)
    assert (new.width, new.height) == size
    uu, vv = new.pixel_grid()
    rays = new.pixel_rays(uu, vv)
    uv_orig, _ = intr.project(rays)
    inner = (slice(2, -2), slice(2, -2))  # skip border pixels where OpenCV clamps
    np.testing.assert_allclose(uv_orig[:, 0].reshape(uu.shape)[inner], u_new[inner], atol=1e-4)
    np.testing.assert_allclose(uv_orig[:, 1].reshape(uu.shape)[inner], v_new[inner], atol=1e-4)


def test_resize_rgbd_never_blends_depth() -> None:
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, size=(48, 64, 3), dtype=np.uint8)
    depth = np.zeros((48, 64), np.float32)
    depth[:, :33] = 1.0  # step edge at an odd column and an invalid region
    depth[:, 40:] = 4.0
    for factor in (0.5, 0.3, 1.7):
        rgb_s, depth_s = resize_rgbd(rgb, depth, factor)
        w, h = scaled_size(64, 48, factor)
        assert rgb_s.shape == (h, w, 3) and rgb_s.dtype == np.uint8
        assert depth_s.shape == (h, w) and depth_s.dtype == np.float32
        assert set(np.unique(depth_s)) <= {0.0, 1.0, 4.0}
    rgb_same, depth_same = resize_rgbd(rgb, depth, 1.0)
    np.testing.assert_array_equal(rgb_same, rgb)
    assert depth_same is not depth
    # colour is area-averaged: a 2x2 block averages
    flat = np.zeros((2, 2, 3), np.uint8)
    flat[0, 0] = 200
    rgb_half, _ = resize_rgbd(flat, np.zeros((2, 2), np.float32), 0.5)
    np.testing.assert_array_equal(rgb_half[0, 0], [50, 50, 50])
    with pytest.raises(ValueError, match="does not match"):
        resize_rgbd(rgb, depth[:10], 0.5)
    with pytest.raises(ValueError, match="rgb"):
        resize_rgbd(rgb[..., 0], depth, 0.5)


@pytest.mark.parametrize("factor", [0.5, 0.3, 1.7])
def test_resized_depth_is_registered_to_the_scaled_intrinsics(factor: float) -> None:
    """A slanted plane's depth, resized, is the plane's depth along the scaled intrinsics'
    rays (OpenCV's nearest-neighbour resize took each block's top-left pixel: half a source
    pixel off, up to 0.36 % of depth here at factor 0.5)."""
    intr = small_intr()
    u, v = intr.pixel_grid()

    def plane(i: Intrinsics, uu: np.ndarray) -> np.ndarray:  # z = 2 + 0.3 x
        return 2.0 / (1.0 - 0.3 * (uu - i.cx) / i.fx)

    rgb = np.zeros((*intr.shape, 3), np.uint8)
    _, depth = resize_rgbd(rgb, plane(intr, u).astype(np.float32), factor)
    new = intr.scaled(factor)
    uu, _ = new.pixel_grid()
    inner = (slice(2, -2), slice(2, -2))
    np.testing.assert_allclose(depth[inner], plane(new, uu)[inner], rtol=2e-4)


def test_torch_helpers_match_numpy() -> None:
    intr = small_intr()
    depth = np.random.default_rng(1).uniform(0.0, 3.0, size=intr.shape).astype(np.float32)
    for dtype in (torch.float32, torch.float64):
        xyz_t = backproject_torch(intr, torch.from_numpy(depth).to(dtype))
        assert xyz_t.dtype == dtype and xyz_t.shape == (48, 64, 3)
        np.testing.assert_allclose(xyz_t.numpy(), intr.backproject(depth), rtol=1e-5, atol=1e-6)
    u = torch.tensor([0.0, 10.5, 63.0], dtype=torch.float64)
    v = torch.tensor([0.0, 20.0, 47.0], dtype=torch.float64)
    rays_t = pixel_rays_torch(intr, u, v)
    assert rays_t.dtype == torch.float64
    np.testing.assert_allclose(rays_t.numpy(), intr.pixel_rays(u.numpy(), v.numpy()))
    rays_int = pixel_rays_torch(intr, torch.tensor([1, 2]), torch.tensor([3, 4]))
    assert rays_int.is_floating_point()
    depth_t = torch.from_numpy(depth).requires_grad_(True)
    backproject_torch(intr, depth_t).sum().backward()
    assert torch.isfinite(depth_t.grad).all()
    with pytest.raises(ValueError, match="backproject_torch"):
        backproject_torch(intr, torch.zeros(3, 3))


def _slanted_plane(height: int = 120, width: int = 160) -> np.ndarray:
    """Depth of a slanted wall 1.6-2.5 m away (its inverse depth is linear in u and v)."""
    u = np.linspace(-1.0, 1.0, width)[None, :]
    v = np.linspace(-1.0, 1.0, height)[:, None]
    return 1.0 / (0.5 + 0.1 * u + 0.05 * v)


@pytest.mark.parametrize("k", [0.3, 1.0, 3.0])
def test_depth_noise_recovers_noise_that_grows_as_depth_squared(k: float) -> None:
    rng = np.random.default_rng(int(k * 10))
    plane = _slanted_plane()
    noisy = plane + rng.normal(0.0, k * 1e-3, plane.shape) * plane**2
    assert depth_noise(noisy) == pytest.approx(k, rel=0.1)
    # holes and a depth edge (another wall 1 m nearer) leave the estimate where it was
    near = plane - 1.0
    noisy[:, 100:] = (near + rng.normal(0.0, k * 1e-3, plane.shape) * near**2)[:, 100:]
    noisy[40:50, 20:60] = 0.0
    noisy[0, :5] = np.nan
    assert depth_noise(noisy) == pytest.approx(k, rel=0.15)


def test_depth_noise_of_exact_depth_is_its_storage_rounding() -> None:
    plane = _slanted_plane()
    assert depth_noise(plane) < 1e-6
    # stored in 0.2 mm steps: sigma 0.058 mm, 0.01-0.02 mm/m² at 1.6-2.5 m
    assert depth_noise(np.round(plane * 5000) / 5000) < 0.05
    assert depth_noise(np.zeros((8, 8))) == 0.0 and depth_noise(np.ones((2, 2))) == 0.0
    with pytest.raises(ValueError, match="keep"):
        depth_noise(plane, keep=1.0)
