"""Furniture for synthetic rooms: pieces along the walls, low pieces in the middle, pictures.

Pieces are built from boxes and prisms in a wall's local frame (`WallFrame`: `a` along the
wall, `d` out from it into the room, `z` up). Anything taller than the room's `low_top` stays
within `band` of a furnished wall, which is what lets trajectories keep their clearance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cpslam.tools.synth.builder import MeshBuilder
from cpslam.tools.synth.texture import MaterialTable, hsv

Rect = tuple[float, float, float, float]  # x0, y0, x1, y1 on the floor


@dataclass(frozen=True)
class Piece:
    """A placed piece of furniture: its room, the wall it stands at, its kind and centre."""

    room: str
    side: str
    name: str
    xy: tuple[float, float]


@dataclass(frozen=True)
class WallFrame:
    """Local frame of a wall: `origin` (xy) at one end of its inner surface, `along` its unit
    direction (counter-clockwise around the room), the room on its left."""

    origin: np.ndarray
    along: np.ndarray
    length: float

    @property
    def inward(self) -> np.ndarray:
        return np.array([-self.along[1], self.along[0]])

    def point(self, a: float, d: float) -> np.ndarray:
        return self.origin + a * self.along + d * self.inward

    def along_of(self, xy: np.ndarray) -> float:
        return float((np.asarray(xy) - self.origin) @ self.along)

    def rect(self, a0: float, a1: float, d0: float, d1: float) -> Rect:
        p, q = self.point(a0, d0), self.point(a1, d1)
        return (min(p[0], q[0]), min(p[1], q[1]), max(p[0], q[0]), max(p[1], q[1]))

    def box(self, builder: MeshBuilder, a0: float, a1: float, d0: float, d1: float,
            z0: float, z1: float, material: int) -> None:
        x0, y0, x1, y1 = self.rect(a0, a1, d0, d1)
        builder.box((x0, y0, z0), (x1, y1, z1), material, skip=("-z",) if z0 <= 0 else ())

    def cylinder(self, builder: MeshBuilder, a: float, d: float, radius: float, z0: float,
                 z1: float, material: int) -> None:
        xy = self.point(a, d)
        builder.cylinder((float(xy[0]), float(xy[1])), radius, z0, z1, material)

    def wall_quad(self, builder: MeshBuilder, a0: float, a1: float, z0: float, z1: float,
                  material: int) -> None:
        p, q = self.point(a0, 0.0), self.point(a1, 0.0)
        corners = np.array([[p[0], p[1], z0], [q[0], q[1], z0], [q[0], q[1], z1],
                            [p[0], p[1], z1]])
        builder.quad(corners, np.r_[self.inward, 0.0], material)


# Along-wall pieces per room kind: name -> (weight, width range, at most this many per room).
_CATALOGUE: dict[str, dict[str, tuple[float, tuple[float, float], int]]] = {
    "living": {"sofa": (2, (1.6, 2.1), 1), "bookshelf": (2, (0.7, 1.1), 3),
               "tv": (1.5, (1.2, 1.6), 1), "plant": (1, (0.5, 0.6), 2),
               "lamp": (1, (0.45, 0.5), 2), "cabinet": (1, (0.8, 1.3), 2)},
    "bedroom": {"bed": (3, (1.4, 1.6), 1), "wardrobe": (2, (0.9, 1.3), 2),
                "cabinet": (1.5, (0.8, 1.3), 2), "plant": (1, (0.5, 0.6), 2),
                "lamp": (1, (0.45, 0.5), 1)},
    "office": {"desk": (3, (1.0, 1.4), 2), "bookshelf": (2, (0.7, 1.1), 3),
               "cabinet": (1, (0.8, 1.2), 2), "plant": (1, (0.5, 0.6), 2)},
    "kitchen": {"counter": (3, (1.2, 2.2), 2), "fridge": (1.5, (0.6, 0.75), 1),
                "cabinet": (1, (0.8, 1.2), 1), "plant": (1, (0.5, 0.6), 1)},
}


class Furnisher:
    """Places the furniture of one room (deterministic given the generator's state)."""

    def __init__(self, builder: MeshBuilder, mats: MaterialTable, rng: np.random.Generator,
                 room: str, kind: str, hue: float) -> None:
        if kind not in _CATALOGUE:
            raise ValueError(f"room {room!r}: unknown kind {kind!r}; expected one of "
                             + ", ".join(_CATALOGUE))
        self.b, self.mats, self.rng = builder, mats, rng
        self.room, self.kind, self.hue = room, kind, hue
        self.occupied: list[Rect] = []
        self.counts: dict[str, int] = {}
        self.pieces: list[Piece] = []
        self._n = 0

    def furnish(self, frames: dict[str, WallFrame], furnished: tuple[str, ...],
                door_spans: dict[str, list[tuple[float, float]]], room_lo: np.ndarray,
                room_hi: np.ndarray, height: float) -> None:
        """Fill the furnished walls, then the middle of the room, then hang pictures.

        The pieces keep to the scene's rules by construction (each builder's sizes): nothing
        above 0.55 m deeper than 0.6 m from its wall, nothing in the middle above 0.55 m.
        """
        piece_spans: dict[str, list[tuple[float, float]]] = {s: [] for s in frames}
        for side, spans in door_spans.items():  # keep doorways and their approach free
            for lo, hi in spans:
                self.occupied.append(frames[side].rect(lo - 0.3, hi + 0.3, 0.0, 1.4))
        for side in furnished:
            piece_spans[side] = self._fill_wall(frames[side], side)
        self._middle(room_lo, room_hi)
        for side, frame in frames.items():
            blocked = piece_spans[side] + [(lo - 0.15, hi + 0.15) for lo, hi in door_spans[side]]
            self._pictures(frame, blocked, height)

    # -- placement -------------------------------------------------------------------------

    def _fill_wall(self, f: WallFrame, side: str) -> list[tuple[float, float]]:
        """Place pieces left to right along one wall; returns the spans they take."""
        spans = []
        cursor = self.rng.uniform(0.05, 0.3)
        catalogue = _CATALOGUE[self.kind]
        while cursor < f.length - 0.4:
            names = [n for n, (_, _, most) in catalogue.items() if self.counts.get(n, 0) < most]
            if not names:
                break
            weights = np.array([catalogue[n][0] for n in names], dtype=float)
            name = names[int(self.rng.choice(len(names), p=weights / weights.sum()))]
            lo, hi = catalogue[name][1]
            width = self.rng.uniform(lo, hi)
            gap = self.rng.uniform(0.05, 0.35)
            if cursor + width > f.length - 0.02:
                cursor += 0.25
                continue
            depth = _FOOTPRINT_DEPTH[name]
            rect = f.rect(cursor, cursor + width, 0.0, depth)
            if self._overlaps(rect):
                cursor += 0.25
                continue
            self.occupied.append(rect)
            self.counts[name] = self.counts.get(name, 0) + 1
            getattr(self, "_" + name)(f, cursor, cursor + width)
            centre = f.point(cursor + 0.5 * width, 0.5 * min(depth, 1.0))
            self.pieces.append(Piece(self.room, side, name, (float(centre[0]),
                                                             float(centre[1]))))
            spans.append((cursor, cursor + width))
            cursor += width + gap
        return spans

    def _middle(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """A rug and a low piece or two somewhere in the room."""
        for name, size in (("rug", (2.0, 1.4)), ("table", (1.0, 0.6)), ("stool", (0.45, 0.45))):
            if name == "table" and self.kind not in ("living", "office"):
                continue
            for _ in range(25):
                w, h = size[0] * self.rng.uniform(0.8, 1.1), size[1] * self.rng.uniform(0.8, 1.1)
                cx = self.rng.uniform(lo[0] + 0.5 * w + 0.05, hi[0] - 0.5 * w - 0.05)
                cy = self.rng.uniform(lo[1] + 0.5 * h + 0.05, hi[1] - 0.5 * h - 0.05)
                rect = (cx - 0.5 * w, cy - 0.5 * h, cx + 0.5 * w, cy + 0.5 * h)
                if self._overlaps(rect):
                    continue
                if name != "rug":  # other low pieces may stand on the rug
                    self.occupied.append(rect)
                getattr(self, "_" + name)(rect)
                break

    def _pictures(self, f: WallFrame, blocked: list[tuple[float, float]], height: float
                  ) -> None:
        for _ in range(int(self.rng.integers(1, 3))):
            w = self.rng.uniform(0.4, 0.9)
            h = self.rng.uniform(0.3, 0.6)
            a0 = self.rng.uniform(0.1, max(0.11, f.length - w - 0.1))
            if any(a0 < hi and a0 + w > lo for lo, hi in blocked):
                continue
            blocked.append((a0 - 0.1, a0 + w + 0.1))
            z0 = self.rng.uniform(1.3, 1.7) - 0.5 * h
            frame = self._mat("frame", "wood", (0.05, 0.5), (0.2, 0.6), 0.05)
            pattern = str(self.rng.choice(["checker", "dots", "stripes", "plaster", "tiles"]))
            canvas = self.mats.add(f"{self.room}/picture{self._n}", pattern,
                                   hsv(self.rng.random(), self.rng.uniform(0.4, 0.9), 0.85),
                                   hsv(self.rng.random(), self.rng.uniform(0.4, 0.9), 0.35),
                                   self.rng.uniform(0.05, 0.15))
            f.box(self.b, a0, a0 + w, 0.0, 0.03, z0, min(z0 + h, height - 0.1), frame)
            f.box(self.b, a0 + 0.04, a0 + w - 0.04, 0.03, 0.04, z0 + 0.04,
                  min(z0 + h, height - 0.1) - 0.04, canvas)

    def _overlaps(self, rect: Rect) -> bool:
        x0, y0, x1, y1 = rect
        return any(x0 < q[2] and q[0] < x1 and y0 < q[3] and q[1] < y1 for q in self.occupied)

    def _mat(self, what: str, pattern: str, hue_range: tuple[float, float],
             value_range: tuple[float, float], scale: float, saturation: float = 0.5) -> int:
        """A new material for one part of a piece (each piece gets its own colours)."""
        self._n += 1
        rng = self.rng
        a = hsv(rng.uniform(*hue_range), saturation * rng.uniform(0.6, 1.2),
                rng.uniform(*value_range))
        b = hsv(rng.uniform(0, 1), rng.uniform(0.2, 0.6), rng.uniform(0.15, 0.5))
        return self.mats.add(f"{self.room}/{what}{self._n}", pattern, a, b, scale)

    def _any_mat(self, what: str) -> int:
        pattern = str(self.rng.choice(["plain", "stripes", "checker", "plaster", "dots"]))
        return self._mat(what, pattern, (0.0, 1.0), (0.35, 0.85),
                         float(self.rng.uniform(0.04, 0.15)), saturation=0.8)

    # -- pieces along a wall (a0..a1 along the wall) ---------------------------------------

    def _bookshelf(self, f: WallFrame, a0: float, a1: float) -> None:
        wood = self._mat("shelf", "wood", (0.04, 0.12), (0.3, 0.75), 0.08)
        depth, top, t = self.rng.uniform(0.3, 0.36), self.rng.uniform(1.7, 2.0), 0.02
        f.box(self.b, a0, a0 + t, 0.01, depth, 0, top, wood)
        f.box(self.b, a1 - t, a1, 0.01, depth, 0, top, wood)
        f.box(self.b, a0 + t, a1 - t, 0.01, depth, top - t, top, wood)
        f.box(self.b, a0 + t, a1 - t, 0.01, depth, 0, 0.08, wood)
        f.box(self.b, a0 + t, a1 - t, 0.01, 0.025, 0.08, top - t, wood)
        levels = np.linspace(0.08, top - t, 5)
        book_mats = [self._any_mat("books") for _ in range(3)]
        for z0, z1 in zip(levels[:-1], levels[1:], strict=True):
            if z0 > 0.09:
                f.box(self.b, a0 + t, a1 - t, 0.025, depth, z0, z0 + t, wood)
            a = a0 + t + self.rng.uniform(0.0, 0.1)
            while True:
                w = self.rng.uniform(0.02, 0.05)
                if a + w > a1 - t - 0.005:
                    break
                if self.rng.random() < 0.12:
                    a += self.rng.uniform(0.04, 0.12)
                    continue
                hgt = (z1 - z0 - t) * self.rng.uniform(0.55, 0.9)
                mat = book_mats[int(self.rng.integers(0, 3))]
                f.box(self.b, a, a + w, 0.03, 0.03 + self.rng.uniform(0.16, 0.26),
                      z0 + t, z0 + t + hgt, mat)
                a += w + 0.002

    def _cabinet(self, f: WallFrame, a0: float, a1: float) -> None:
        body = self._mat("cabinet", str(self.rng.choice(["wood", "plain", "plaster"])),
                         (0.0, 1.0), (0.45, 0.85), 0.12)
        fronts = self._mat("drawer", str(self.rng.choice(["wood", "stripes", "plain"])),
                           (0.0, 1.0), (0.4, 0.9), 0.06)
        handle = self._mat("handle", "plain", (0.1, 0.15), (0.15, 0.3), 1.0)
        depth, top = self.rng.uniform(0.42, 0.52), self.rng.uniform(0.8, 1.05)
        f.box(self.b, a0, a1, 0.01, depth, 0, top - 0.03, body)
        f.box(self.b, a0 - 0.015, a1 + 0.015, 0.01, depth + 0.02, top - 0.03, top, body)
        cols = 1 if a1 - a0 < 1.0 else 2
        edges_a = np.linspace(a0, a1, cols + 1)
        edges_z = np.linspace(0.06, top - 0.05, 4)
        for c in range(cols):
            for r in range(3):
                lo_a, hi_a = edges_a[c] + 0.01, edges_a[c + 1] - 0.01
                lo_z, hi_z = edges_z[r] + 0.01, edges_z[r + 1] - 0.01
                f.box(self.b, lo_a, hi_a, depth, depth + 0.02, lo_z, hi_z, fronts)
                mid_a, mid_z = 0.5 * (lo_a + hi_a), 0.5 * (lo_z + hi_z)
                f.box(self.b, mid_a - 0.06, mid_a + 0.06, depth + 0.02, depth + 0.04,
                      mid_z - 0.01, mid_z + 0.01, handle)

    def _wardrobe(self, f: WallFrame, a0: float, a1: float) -> None:
        body = self._mat("wardrobe", "wood", (0.0, 1.0), (0.35, 0.8), 0.15)
        doors = self._mat("wardrobe_door", str(self.rng.choice(["plain", "stripes", "wood"])),
                          (0.0, 1.0), (0.45, 0.9), 0.1)
        handle = self._mat("handle", "plain", (0.1, 0.15), (0.1, 0.25), 1.0)
        top = self.rng.uniform(1.9, 2.1)
        f.box(self.b, a0, a1, 0.01, 0.54, 0, top, body)
        mid = 0.5 * (a0 + a1)
        for lo, hi in ((a0 + 0.02, mid - 0.005), (mid + 0.005, a1 - 0.02)):
            f.box(self.b, lo, hi, 0.54, 0.56, 0.08, top - 0.05, doors)
        for a in (mid - 0.05, mid + 0.03):
            f.box(self.b, a, a + 0.02, 0.56, 0.585, 0.9, 1.3, handle)

    def _desk(self, f: WallFrame, a0: float, a1: float) -> None:
        wood = self._mat("desk", str(self.rng.choice(["wood", "plain"])), (0.0, 1.0),
                         (0.4, 0.85), 0.1)
        metal = self._mat("legs", "plain", (0.0, 1.0), (0.15, 0.35), 1.0)
        screen = self._mat("screen", "stripes", (0.55, 0.7), (0.1, 0.25), 0.02)
        depth, top = self.rng.uniform(0.55, 0.58), 0.75
        f.box(self.b, a0, a1, 0.01, depth, top - 0.03, top, wood)
        for a in (a0 + 0.02, a1 - 0.07):
            for d in (0.03, depth - 0.07):
                f.box(self.b, a, a + 0.05, d, d + 0.05, 0.0, top - 0.03, metal)
        mid = a0 + self.rng.uniform(0.35, 0.65) * (a1 - a0)
        f.box(self.b, mid - 0.08, mid + 0.08, 0.08, 0.22, top, top + 0.015, metal)
        f.box(self.b, mid - 0.02, mid + 0.02, 0.12, 0.15, top, top + 0.12, metal)
        f.box(self.b, mid - 0.28, mid + 0.28, 0.15, 0.18, top + 0.1, top + 0.43, screen)
        f.box(self.b, mid - 0.22, mid + 0.22, 0.3, 0.45, top, top + 0.02, self._any_mat("kbd"))
        f.cylinder(self.b, a1 - 0.15, 0.2, 0.06, top, top + 0.25, self._any_mat("cup"))

    def _counter(self, f: WallFrame, a0: float, a1: float) -> None:
        body = self._mat("counter", "plain", (0.0, 1.0), (0.55, 0.9), 1.0, saturation=0.3)
        fronts = self._mat("kitchen_door", str(self.rng.choice(["wood", "plain", "stripes"])),
                           (0.0, 1.0), (0.45, 0.9), 0.08)
        worktop = self._mat("worktop", "plaster", (0.0, 1.0), (0.3, 0.7), 0.3)
        splash = self._mat("splash", "tiles", (0.0, 1.0), (0.6, 0.95), 0.1)
        handle = self._mat("handle", "plain", (0.1, 0.15), (0.1, 0.25), 1.0)
        f.box(self.b, a0, a1, 0.01, 0.55, 0, 0.86, body)
        f.box(self.b, a0, a1, 0.01, 0.59, 0.86, 0.9, worktop)
        f.box(self.b, a0, a1, 0.0, 0.012, 0.9, 1.45, splash)
        f.box(self.b, a0, a1, 0.01, 0.34, 1.45, 2.1, body)
        n = max(1, int(round((a1 - a0) / 0.5)))
        edges = np.linspace(a0, a1, n + 1)
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            f.box(self.b, lo + 0.01, hi - 0.01, 0.55, 0.565, 0.1, 0.84, fronts)
            f.box(self.b, lo + 0.01, hi - 0.01, 0.34, 0.355, 1.47, 2.08, fronts)
            mid = 0.5 * (lo + hi)
            f.box(self.b, mid - 0.05, mid + 0.05, 0.565, 0.585, 0.75, 0.77, handle)
            f.box(self.b, mid - 0.05, mid + 0.05, 0.355, 0.375, 1.52, 1.54, handle)

    def _fridge(self, f: WallFrame, a0: float, a1: float) -> None:
        body = self._mat("fridge", "plain", (0.0, 1.0), (0.75, 0.95), 1.0, saturation=0.15)
        handle = self._mat("handle", "plain", (0.1, 0.15), (0.1, 0.25), 1.0)
        f.box(self.b, a0, a1, 0.01, 0.56, 0, 1.8, body)
        f.box(self.b, a0 + 0.01, a1 - 0.01, 0.56, 0.57, 1.2, 1.78, body)
        f.box(self.b, a0 + 0.01, a1 - 0.01, 0.56, 0.57, 0.05, 1.18, body)
        f.box(self.b, a1 - 0.08, a1 - 0.05, 0.57, 0.595, 0.6, 1.1, handle)
        f.box(self.b, a1 - 0.08, a1 - 0.05, 0.57, 0.595, 1.3, 1.6, handle)

    def _sofa(self, f: WallFrame, a0: float, a1: float) -> None:
        cloth = self._mat("sofa", str(self.rng.choice(["plaster", "checker", "stripes"])),
                          (0.0, 1.0), (0.3, 0.7), 0.08, saturation=0.7)
        cushion = self._any_mat("cushion")
        f.box(self.b, a0, a1, 0.01, 0.22, 0, 0.85, cloth)
        f.box(self.b, a0, a1, 0.22, 0.85, 0, 0.4, cloth)
        for lo in (a0, a1 - 0.15):
            f.box(self.b, lo, lo + 0.15, 0.22, 0.85, 0.4, 0.55, cloth)
        edges = np.linspace(a0 + 0.16, a1 - 0.16, 3)
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            f.box(self.b, lo + 0.01, hi - 0.01, 0.24, 0.82, 0.4, 0.5, cushion)
            f.box(self.b, lo + 0.05, hi - 0.05, 0.22, 0.36, 0.5, 0.8, cushion)

    def _tv(self, f: WallFrame, a0: float, a1: float) -> None:
        stand = self._mat("tvstand", "wood", (0.0, 1.0), (0.25, 0.6), 0.1)
        screen = self._mat("tv", "plaster", (0.55, 0.7), (0.05, 0.2), 0.4)
        f.box(self.b, a0, a1, 0.01, 0.45, 0, 0.5, stand)
        mid, half = 0.5 * (a0 + a1), 0.45 * (a1 - a0) * 0.8
        f.box(self.b, mid - 0.1, mid + 0.1, 0.1, 0.2, 0.5, 0.58, stand)
        f.box(self.b, mid - half, mid + half, 0.14, 0.18, 0.58, 0.58 + 1.1 * half, screen)

    def _bed(self, f: WallFrame, a0: float, a1: float) -> None:
        wood = self._mat("bed", "wood", (0.03, 0.12), (0.3, 0.7), 0.1)
        sheet = self._mat("mattress", "plain", (0.0, 1.0), (0.8, 0.95), 1.0, saturation=0.1)
        blanket = self._mat("blanket", str(self.rng.choice(["checker", "stripes", "dots"])),
                            (0.0, 1.0), (0.45, 0.85), float(self.rng.uniform(0.1, 0.25)),
                            saturation=0.8)
        pillow = self._any_mat("pillow")
        f.box(self.b, a0, a1, 0.01, 0.07, 0, 1.0, wood)
        f.box(self.b, a0, a1, 0.07, 2.05, 0, 0.3, wood)
        f.box(self.b, a0 + 0.02, a1 - 0.02, 0.09, 2.03, 0.3, 0.47, sheet)
        f.box(self.b, a0 + 0.01, a1 - 0.01, 0.7, 2.04, 0.3, 0.5, blanket)
        mid = 0.5 * (a0 + a1)
        for lo, hi in ((a0 + 0.08, mid - 0.04), (mid + 0.04, a1 - 0.08)):
            f.box(self.b, lo, hi, 0.12, 0.45, 0.47, 0.55, pillow)

    def _plant(self, f: WallFrame, a0: float, a1: float) -> None:
        pot = self._mat("pot", str(self.rng.choice(["plain", "stripes", "dots"])), (0.0, 1.0),
                        (0.3, 0.8), 0.05)
        leaves = self._mat("leaves", "plaster", (0.25, 0.4), (0.25, 0.55), 0.08, saturation=1.2)
        mid, r = 0.5 * (a0 + a1), self.rng.uniform(0.15, 0.2)
        top = self.rng.uniform(1.0, 1.6)
        f.cylinder(self.b, mid, 0.3, r, 0.0, 0.4, pot)
        f.cylinder(self.b, mid, 0.3, 0.02, 0.4, 0.55, leaves)
        f.cylinder(self.b, mid, 0.3, 0.27, 0.55, top - 0.25, leaves)
        f.cylinder(self.b, mid, 0.3, 0.17, top - 0.25, top, leaves)

    def _lamp(self, f: WallFrame, a0: float, a1: float) -> None:
        metal = self._mat("lamp", "plain", (0.0, 1.0), (0.1, 0.3), 1.0)
        shade = self._mat("shade", str(self.rng.choice(["plain", "stripes", "plaster"])),
                          (0.0, 1.0), (0.75, 0.95), 0.05)
        mid = 0.5 * (a0 + a1)
        f.cylinder(self.b, mid, 0.3, 0.15, 0.0, 0.03, metal)
        f.cylinder(self.b, mid, 0.3, 0.015, 0.03, 1.4, metal)
        f.cylinder(self.b, mid, 0.3, 0.2, 1.35, 1.65, shade)

    # -- low pieces in the middle (rect on the floor) --------------------------------------

    def _rug(self, rect: Rect) -> None:
        mat = self._mat("rug", str(self.rng.choice(["checker", "stripes", "dots", "tiles"])),
                        (0.0, 1.0), (0.35, 0.8), float(self.rng.uniform(0.12, 0.3)),
                        saturation=0.8)
        self.b.box((rect[0], rect[1], 0.0), (rect[2], rect[3], 0.008), mat, skip=("-z",))

    def _table(self, rect: Rect) -> None:
        wood = self._mat("table", str(self.rng.choice(["wood", "plain"])), (0.0, 1.0),
                         (0.3, 0.8), 0.1)
        x0, y0, x1, y1 = rect
        top = self.rng.uniform(0.4, 0.46)
        self.b.box((x0, y0, top - 0.04), (x1, y1, top), wood)
        for x in (x0 + 0.03, x1 - 0.08):
            for y in (y0 + 0.03, y1 - 0.08):
                self.b.box((x, y, 0.0), (x + 0.05, y + 0.05, top - 0.04), wood, skip=("-z",))
        cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
        self.b.box((cx - 0.15, cy - 0.1, top), (cx + 0.1, cy + 0.08, top + 0.04),
                   self._any_mat("book"))

    def _stool(self, rect: Rect) -> None:
        cx, cy = 0.5 * (rect[0] + rect[2]), 0.5 * (rect[1] + rect[3])
        self.b.cylinder((cx, cy), 0.2, 0.0, self.rng.uniform(0.4, 0.5), self._any_mat("stool"))


_FOOTPRINT_DEPTH = {"bookshelf": 0.4, "cabinet": 0.6, "wardrobe": 0.6, "desk": 0.6,
                    "counter": 0.6, "fridge": 0.6, "sofa": 0.86, "tv": 0.46, "bed": 2.06,
                    "plant": 0.6, "lamp": 0.5}
