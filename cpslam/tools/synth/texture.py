"""Procedural surface textures evaluated at 3-D hit points.

Every triangle of a synthetic scene carries a material id; a `Material` turns the hit point
into a colour through a pattern (stripes, checker, tiles, brick, wood, plaster, dots) in 2-D
surface coordinates. The patterns are sharp, but each one is box-filtered analytically over
the pixel footprint (the width in metres a pixel covers at the hit point), so distant
textures fade to their mean instead of aliasing; that keeps colours stable from frame to
frame, which photometric tracking relies on. Shading is view-independent (two fixed
directional lights plus ambient) so a surface point has the same colour from every view.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PATTERNS = ("plaster", "stripes", "checker", "tiles", "brick", "wood", "dots", "plain")

# Fixed lights (world frame, z up): a key light from above and a weaker fill from the side.
_KEY = np.array([0.35, 0.25, 1.0]) / np.linalg.norm([0.35, 0.25, 1.0])
_FILL = np.array([-0.6, -0.8, 0.25]) / np.linalg.norm([-0.6, -0.8, 0.25])


@dataclass(frozen=True)
class Material:
    """A procedural material: a pattern mixing two colours.

    Attributes:
        name: where it is used, e.g. ``"B/wall_E"`` (room B, east wall).
        pattern: one of `PATTERNS`.
        color_a: main RGB colour in [0, 1].
        color_b: second RGB colour in [0, 1] (stripes, grout, mortar, grain, spots).
        scale: pattern period in metres (tile size, stripe period, brick height, ...).
        seed: seed of the material's value noise and per-cell colour variation.
    """

    name: str
    pattern: str
    color_a: tuple[float, float, float]
    color_b: tuple[float, float, float]
    scale: float
    seed: int

    def __post_init__(self) -> None:
        if self.pattern not in PATTERNS:
            raise ValueError(f"Material {self.name!r}: unknown pattern {self.pattern!r}; "
                             f"expected one of {', '.join(PATTERNS)}")
        if not self.scale > 0:
            raise ValueError(f"Material {self.name!r}: scale must be > 0, got {self.scale}")

    @property
    def mean_color(self) -> np.ndarray:
        """Approximate average colour (what the texture fades to far away)."""
        a, b = np.asarray(self.color_a), np.asarray(self.color_b)
        weight_b = {"plain": 0.0, "dots": 0.25, "tiles": 0.15, "brick": 0.15}.get(self.pattern, 0.5)
        return (1.0 - weight_b) * a + weight_b * b


def shade(
    materials: list[Material],
    material_ids: np.ndarray,
    xyz: np.ndarray,
    normals: np.ndarray,
    footprint: np.ndarray,
) -> np.ndarray:
    """Colour of surface points.

    Args:
        materials: the scene's material table.
        material_ids: [N] index into `materials` per point.
        xyz: [N, 3] world points (z up).
        normals: [N, 3] unit surface normals facing the viewer (sign is used for lighting).
        footprint: [N] width in metres over which to filter the pattern (pixel size at the
            point; use the mesh cell size when colouring a mesh).

    Returns:
        [N, 3] float64 RGB in [0, 1].
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    footprint = np.maximum(np.asarray(footprint, dtype=np.float64), 1e-5)
    rgb = np.zeros((len(xyz), 3))
    if len(xyz) == 0:
        return rgb
    u, v = surface_coords(xyz, normals)
    order = np.argsort(material_ids, kind="stable")
    ids_sorted = material_ids[order]
    bounds = np.flatnonzero(np.diff(ids_sorted)) + 1
    for group in np.split(order, bounds):
        mat = materials[int(material_ids[group[0]])]
        rgb[group] = _pattern(mat, u[group], v[group], footprint[group])
    light = (0.58 + 0.30 * np.clip(np.einsum("ij,j->i", normals, _KEY), 0.0, None)
             + 0.17 * np.clip(np.einsum("ij,j->i", normals, _FILL), 0.0, None))
    return np.clip(rgb * light[:, None], 0.0, 1.0)


def surface_coords(xyz: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """2-D texture coordinates in metres: (x, y) on floors/ceilings, (along, z) on walls.

    On non-horizontal faces `along` is the position along the horizontal tangent z × n, so
    axis-aligned walls get continuous coordinates and each facet of a prism gets its own.
    """
    horizontal = np.abs(normals[:, 2]) >= 0.9
    tangent = np.stack([-normals[:, 1], normals[:, 0], np.zeros(len(normals))], axis=1)
    norm = np.linalg.norm(tangent, axis=1, keepdims=True)
    tangent = tangent / np.maximum(norm, 1e-12)
    along = np.einsum("ij,ij->i", xyz, tangent)
    u = np.where(horizontal, xyz[:, 0], along)
    v = np.where(horizontal, xyz[:, 1], xyz[:, 2])
    return u, v


def value_noise(u: np.ndarray, v: np.ndarray, seed: int) -> np.ndarray:
    """Smooth 2-D value noise in [0, 1] with unit lattice spacing (quintic interpolation)."""
    iu, iv = np.floor(u), np.floor(v)
    fu, fv = u - iu, v - iv
    iu, iv = iu.astype(np.int64), iv.astype(np.int64)
    su = fu * fu * fu * (fu * (fu * 6.0 - 15.0) + 10.0)
    sv = fv * fv * fv * (fv * (fv * 6.0 - 15.0) + 10.0)
    n00 = cell_hash(iu, iv, seed)
    n10 = cell_hash(iu + 1, iv, seed)
    n01 = cell_hash(iu, iv + 1, seed)
    n11 = cell_hash(iu + 1, iv + 1, seed)
    return (n00 * (1 - su) + n10 * su) * (1 - sv) + (n01 * (1 - su) + n11 * su) * sv


def cell_hash(i: np.ndarray, j: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) per integer cell (i, j).

    A 32-bit integer mix (uint32 arithmetic wraps, which is what the hash wants).
    """
    h = i.astype(np.uint32) * np.uint32(0x9E3779B1)
    h ^= j.astype(np.uint32) * np.uint32(0x85EBCA77)
    h ^= np.uint32((seed * 0xC2B2AE3D) & 0xFFFFFFFF)
    h ^= h >> np.uint32(15)
    h *= np.uint32(0x2C1B3C6D)
    h ^= h >> np.uint32(12)
    h *= np.uint32(0x297A2D39)
    h ^= h >> np.uint32(15)
    return h.astype(np.float64) * (1.0 / 4294967296.0)


def _fbm(u: np.ndarray, v: np.ndarray, seed: int, footprint: np.ndarray, octaves: int = 3,
         ) -> np.ndarray:
    """Fractal noise in about [0, 1]; octaves finer than the footprint fade to their mean."""
    total = np.zeros_like(u)
    weight_sum = 0.0
    freq, amp = 1.0, 1.0
    for k in range(octaves):
        fade = np.clip(1.5 - footprint * freq * 2.0, 0.0, 1.0)
        total += amp * (0.5 + fade * (value_noise(u * freq, v * freq, seed + 101 * k) - 0.5))
        weight_sum += amp
        freq, amp = freq * 2.0, amp * 0.5
    return total / weight_sum


def _pulse(x: np.ndarray, duty: float, width: np.ndarray) -> np.ndarray:
    """Square wave (1 where frac(x) < duty, period 1) box-filtered over `width` periods.

    The filter is exact: the difference of the wave's integral at both ends of the box.
    """
    width = np.maximum(width, 1e-6)

    def integral(t: np.ndarray) -> np.ndarray:
        whole = np.floor(t)
        return whole * duty + np.minimum(t - whole, duty)

    return (integral(x + 0.5 * width) - integral(x - 0.5 * width)) / width


def _smoothstep(e0: np.ndarray | float, e1: np.ndarray | float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / np.maximum(np.asarray(e1) - e0, 1e-9), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    return a[None, :] * (1.0 - t[:, None]) + b[None, :] * t[:, None]


def _pattern(mat: Material, u: np.ndarray, v: np.ndarray, footprint: np.ndarray) -> np.ndarray:
    """RGB in [0, 1] of one material at surface coordinates (u, v) in metres."""
    a, b = np.asarray(mat.color_a, dtype=np.float64), np.asarray(mat.color_b, dtype=np.float64)
    s = mat.scale
    w = footprint / s  # footprint in pattern periods
    # Low-frequency brightness drift (period ~0.8 m) breaks the repetition of every pattern,
    # which gives place recognition something to hold on to.
    drift = 0.92 + 0.16 * value_noise(u / 0.8, v / 0.8, mat.seed + 7)
    if mat.pattern == "plain":
        rgb = np.broadcast_to(a, (len(u), 3)).copy()
    elif mat.pattern == "plaster":
        n = _fbm(u / s, v / s, mat.seed, w)
        # Blotches: a thresholded noise with a footprint-wide transition gives sharp-edged
        # stains that are still filtered.
        edge = 0.02 + w
        blot = _smoothstep(0.62 - edge, 0.62 + edge, n)
        rgb = _mix(a, b, 0.25 * n + 0.75 * blot)
    elif mat.pattern == "stripes":
        t = _pulse(u / s, 0.5, w)
        rgb = _mix(a, b, t)
        rgb *= (0.94 + 0.12 * _fbm(u / (3 * s), v / (3 * s), mat.seed, w / 3))[:, None]
    elif mat.pattern == "checker":
        pu, pv = _pulse(u / s, 0.5, w), _pulse(v / s, 0.5, w)
        rgb = _mix(a, b, pu + pv - 2.0 * pu * pv)
    elif mat.pattern == "tiles":
        grout_u, grout_v = _pulse(u / s, 0.06, w), _pulse(v / s, 0.06, w)
        grout = grout_u + grout_v - grout_u * grout_v
        cell = cell_hash(np.floor(u / s).astype(np.int64), np.floor(v / s).astype(np.int64),
                         mat.seed)
        shade_cell = 1.0 + 0.25 * (cell - 0.5) * np.clip(1.0 - w, 0.0, 1.0)
        rgb = _mix(a * 1.0, b, grout) * np.where(grout < 0.5, shade_cell, 1.0)[:, None]
    elif mat.pattern == "brick":
        row = np.floor(v / s)
        along = u / (2.2 * s) + 0.5 * (row.astype(np.int64) % 2)
        mortar_h = _pulse(v / s, 0.12, w)
        mortar_v = _pulse(along, 0.05, w / 2.2)
        mortar = mortar_h + mortar_v - mortar_h * mortar_v
        cell = cell_hash(np.floor(along).astype(np.int64), row.astype(np.int64), mat.seed)
        brick = a[None, :] * (0.8 + 0.4 * cell * np.clip(1.0 - w, 0.0, 1.0))[:, None]
        rgb = brick * (1.0 - mortar[:, None]) + b[None, :] * mortar[:, None]
    elif mat.pattern == "wood":
        plank = np.floor(v / s)
        seam = _pulse(v / s, 0.04, w)
        warp = _fbm(u / (4 * s), v / s * 3.0, mat.seed, w)
        freq = 9.0
        grain_amp = np.clip(1.0 - w * freq * 1.5, 0.0, 1.0)
        grain = 0.5 + 0.5 * grain_amp * np.sin(2 * np.pi * (v / s * freq + 3.0 * warp))
        tint = 0.85 + 0.3 * cell_hash(plank.astype(np.int64), np.zeros_like(plank, np.int64),
                                      mat.seed)
        rgb = _mix(a, b, 0.6 * grain) * tint[:, None]
        rgb = rgb * (1.0 - 0.55 * seam[:, None])
    elif mat.pattern == "dots":
        cu, cv = u / s - np.floor(u / s) - 0.5, v / s - np.floor(v / s) - 0.5
        dist = np.hypot(cu, cv)
        t = 1.0 - _smoothstep(0.28 - w, 0.28 + w, dist)
        # Far away the dots blur into their area fraction (pi * 0.28^2 ~ 0.25).
        far = np.clip(1.5 * w - 0.2, 0.0, 1.0)
        rgb = _mix(a, b, t * (1.0 - far) + 0.25 * far)
    else:  # pragma: no cover - guarded by Material.__post_init__
        raise ValueError(mat.pattern)
    return rgb * drift[:, None]


class MaterialTable:
    """The scene's list of materials; `add` returns the id triangles refer to.

    Each material gets its own noise seed drawn from the scene's generator, so the same scene
    seed gives the same textures.
    """

    def __init__(self, rng: np.random.Generator) -> None:
        self.materials: list[Material] = []
        self._rng = rng

    def add(self, name: str, pattern: str, color_a: tuple[float, float, float],
            color_b: tuple[float, float, float], scale: float) -> int:
        seed = int(self._rng.integers(0, 2**31 - 1))
        self.materials.append(Material(name, pattern, tuple(map(float, color_a)),
                                       tuple(map(float, color_b)), float(scale), seed))
        return len(self.materials) - 1


def hsv(h: float, s: float, v: float) -> tuple[float, float, float]:
    """RGB in [0, 1] from hue (wraps), saturation and value."""
    h = (h % 1.0) * 6.0
    k = int(h) % 6
    f = h - int(h)
    p, q, t = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
    return [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][k]
