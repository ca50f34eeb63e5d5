"""Triangle-mesh builder for synthetic scenes: quads, boxes and prisms with a material each."""

from __future__ import annotations

import numpy as np

# Face order of `MeshBuilder.box` materials: -x, +x, -y, +y, -z (bottom), +z (top).
FACES = ("-x", "+x", "-y", "+y", "-z", "+z")


class MeshBuilder:
    """Accumulates triangles with one material id per triangle.

    Faces are wound counter-clockwise seen from the side their normal points to (outward for
    solids, into the room for walls), so the mesh renders correctly in viewers that cull back
    faces. Vertices are not shared between faces: every face keeps its own material.
    """

    def __init__(self) -> None:
        self._vertices: list[np.ndarray] = []
        self._triangles: list[np.ndarray] = []
        self._materials: list[np.ndarray] = []
        self._count = 0

    def quad(self, corners: np.ndarray, normal: np.ndarray, material: int) -> None:
        """Add a planar quad given 4 corners in order around it and the side it faces."""
        corners = np.asarray(corners, dtype=np.float64).reshape(4, 3)
        face_normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
        if face_normal @ np.asarray(normal, dtype=np.float64) < 0:
            corners = corners[::-1]
        self._add(corners, np.array([[0, 1, 2], [0, 2, 3]]), material)

    def box(
        self,
        lo: np.ndarray,
        hi: np.ndarray,
        material: int | tuple[int, ...],
        skip: tuple[str, ...] = (),
    ) -> None:
        """Add an axis-aligned box [lo, hi] (world metres) with outward faces.

        Args:
            material: one id for all faces, or six in `FACES` order.
            skip: faces to leave out (hidden ones, e.g. "-z" for a box standing on the floor).
        """
        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        if np.any(hi - lo <= 0):
            raise ValueError(f"box: expected lo < hi on every axis, got lo={lo}, hi={hi}")
        mats = (material,) * 6 if isinstance(material, int) else tuple(material)
        if len(mats) != 6:
            raise ValueError(f"box: expected 1 or 6 materials, got {len(mats)}")
        for face, mat in zip(FACES, mats, strict=True):
            if face in skip:
                continue
            axis = "xyz".index(face[1])
            level = hi[axis] if face[0] == "+" else lo[axis]
            a, b = [k for k in range(3) if k != axis]
            corners = np.zeros((4, 3))
            corners[:, axis] = level
            corners[:, a] = [lo[a], hi[a], hi[a], lo[a]]
            corners[:, b] = [lo[b], lo[b], hi[b], hi[b]]
            normal = np.zeros(3)
            normal[axis] = 1.0 if face[0] == "+" else -1.0
            self.quad(corners, normal, mat)

    def cylinder(
        self,
        center_xy: tuple[float, float],
        radius: float,
        z0: float,
        z1: float,
        material: int,
        sides: int = 20,
        bottom: bool = False,
    ) -> None:
        """Add a vertical prism approximating a cylinder (side facets and a top cap)."""
        if radius <= 0 or z1 <= z0:
            raise ValueError(f"cylinder: expected radius > 0 and z1 > z0, got {radius}, "
                             f"{z0}, {z1}")
        angles = 2 * np.pi * np.arange(sides) / sides
        ring = np.stack([center_xy[0] + radius * np.cos(angles),
                         center_xy[1] + radius * np.sin(angles)], axis=1)
        for k in range(sides):
            p, q = ring[k], ring[(k + 1) % sides]
            corners = np.array([[p[0], p[1], z0], [q[0], q[1], z0],
                                [q[0], q[1], z1], [p[0], p[1], z1]])
            mid = 0.5 * (p + q) - np.asarray(center_xy)
            self.quad(corners, np.array([mid[0], mid[1], 0.0]), material)
        caps = [(z1, 1.0)] + ([(z0, -1.0)] if bottom else [])
        for z, sign in caps:
            centre = np.array([[center_xy[0], center_xy[1], z]])
            rim = np.concatenate([ring, np.full((sides, 1), z)], axis=1)
            k = np.arange(sides)
            tris = np.stack([np.zeros(sides, int), 1 + k, 1 + (k + 1) % sides], axis=1)
            if sign < 0:
                tris = tris[:, [0, 2, 1]]
            self._add(np.concatenate([centre, rim]), tris, material)

    def build(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(vertices [V, 3] float64, triangles [T, 3] int64, material_ids [T] int32)."""
        if not self._triangles:
            raise ValueError("MeshBuilder.build: no geometry was added")
        return (np.concatenate(self._vertices), np.concatenate(self._triangles),
                np.concatenate(self._materials).astype(np.int32))

    def _add(self, vertices: np.ndarray, triangles: np.ndarray, material: int) -> None:
        self._vertices.append(vertices)
        self._triangles.append(triangles.astype(np.int64) + self._count)
        self._materials.append(np.full(len(triangles), material, dtype=np.int32))
        self._count += len(vertices)
