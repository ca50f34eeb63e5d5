"""Synthetic indoor scenes: a furnished `room` or an `apartment` of four connected rooms.

World frame: metres, z up, floor at z = 0. Rooms are axis-aligned; walls are single planes
inset half a wall thickness from the nominal room outline, so neighbouring rooms' walls never
coincide, and doorways have reveals (jambs, lintel, threshold) across the wall thickness.

The layout is fixed per scene name; the seed chooses room kinds, furniture, textures and
colours. A camera anywhere in a room's `free_zone` at a height in `CAMERA_Z` is at least
`CLEARANCE` from all geometry: tall furniture stands only in a band of depth `BAND` along the
walls that carry furniture, and free-standing furniture is lower than `LOW_TOP`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cpslam.tools.synth.builder import MeshBuilder
from cpslam.tools.synth.furniture import Furnisher, Piece, WallFrame
from cpslam.tools.synth.texture import Material, MaterialTable, hsv

SCENES = ("room", "apartment")

ROOM_HEIGHT = 2.6
WALL_HALF = 0.05
DOOR_WIDTH = 1.2
DOOR_HEIGHT = 2.1
BAND = 0.6  # depth of the furniture band along furnished walls
LOW_TOP = 0.55  # free-standing furniture is lower than this
CLEARANCE = 0.5  # minimum camera distance to any surface
CAMERA_Z = (1.2, 1.5)  # camera heights trajectories keep to (doorway lintels at 2.1)
_MARGIN = 0.05


@dataclass(frozen=True)
class Room:
    """One rectangular room; `lo`/`hi` are its inner wall surfaces (x, y)."""

    name: str
    kind: str
    lo: tuple[float, float]
    hi: tuple[float, float]
    furnished: tuple[str, ...]  # sides ("W", "E", "S", "N") with a furniture band

    @property
    def center(self) -> np.ndarray:
        return 0.5 * (np.asarray(self.lo) + np.asarray(self.hi))

    def free_zone(self) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1) where a camera keeps `CLEARANCE` from walls and furniture."""
        deep, shallow = BAND + CLEARANCE + _MARGIN, CLEARANCE + 0.15

        def inset(side: str) -> float:
            return deep if side in self.furnished else shallow

        return (self.lo[0] + inset("W"), self.lo[1] + inset("S"),
                self.hi[0] - inset("E"), self.hi[1] - inset("N"))

    def focus(self) -> np.ndarray:
        """A point worth looking at: the middle of the furnished walls, 0.9 m high."""
        points = [self.wall_frame(side).point(0.5 * self.wall_frame(side).length, 0.3)
                  for side in self.furnished]
        xy = np.mean(points, axis=0) if points else self.center
        return np.array([xy[0], xy[1], 0.9])

    def wall_frame(self, side: str) -> WallFrame:
        (x0, y0), (x1, y1) = self.lo, self.hi
        frames = {
            "S": ((x0, y0), (1.0, 0.0), x1 - x0),
            "E": ((x1, y0), (0.0, 1.0), y1 - y0),
            "N": ((x1, y1), (-1.0, 0.0), x1 - x0),
            "W": ((x0, y1), (0.0, -1.0), y1 - y0),
        }
        origin, along, length = frames[side]
        return WallFrame(np.asarray(origin), np.asarray(along), length)


@dataclass(frozen=True)
class Door:
    """A doorway between rooms `a` and `b` in a wall x = const (axis 0) or y = const (1)."""

    a: str
    b: str
    center: tuple[float, float]
    axis: int
    width: float = DOOR_WIDTH
    height: float = DOOR_HEIGHT

    def side_of(self, room: Room) -> str:
        """Which wall of `room` the door is in."""
        c = self.center[self.axis]
        if self.axis == 0:
            return "W" if abs(room.lo[0] - c) < abs(room.hi[0] - c) else "E"
        return "S" if abs(room.lo[1] - c) < abs(room.hi[1] - c) else "N"

    def normal_from(self, room: Room) -> np.ndarray:
        """Unit xy vector through the door, pointing out of `room`."""
        n = np.zeros(2)
        n[self.axis] = 1.0 if self.side_of(room) in ("E", "N") else -1.0
        return n


@dataclass
class Scene:
    """A triangle mesh with a material per triangle, plus the layout trajectories use."""

    name: str
    seed: int
    vertices: np.ndarray  # [V, 3] float64 world (z up)
    triangles: np.ndarray  # [T, 3] int64
    material_ids: np.ndarray  # [T] int32 into `materials`
    materials: list[Material]
    rooms: tuple[Room, ...]
    doors: tuple[Door, ...]
    pieces: tuple[Piece, ...]  # furniture along the walls

    def room(self, name: str) -> Room:
        for room in self.rooms:
            if room.name == name:
                return room
        raise KeyError(f"scene {self.name!r} has no room {name!r}; rooms: "
                       + ", ".join(r.name for r in self.rooms))

    def door_between(self, a: str, b: str) -> Door:
        for door in self.doors:
            if {door.a, door.b} == {a, b}:
                return door
        raise KeyError(f"scene {self.name!r}: no door between rooms {a!r} and {b!r}")

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices.min(axis=0), self.vertices.max(axis=0)


def build_scene(name: str, seed: int = 0) -> Scene:
    """Build scene `name` ("room" or "apartment"); the same seed gives the same scene."""
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; expected one of {', '.join(SCENES)}")
    rng = np.random.default_rng(seed)
    if name == "room":
        rooms = [_room("R", "living", (0.0, 0.0), (6.0, 5.0), ("W", "E", "S", "N"))]
        doors: list[Door] = []
    else:
        kinds = [str(k) for k in rng.permutation(["living", "bedroom", "office", "kitchen"])]
        rooms = [
            _room("A", kinds[0], (0.0, 0.0), (4.0, 3.6), ("W", "S")),
            _room("B", kinds[1], (4.0, 0.0), (8.0, 3.6), ("E", "S")),
            _room("C", kinds[2], (4.0, 3.6), (8.0, 7.2), ("E", "N")),
            _room("D", kinds[3], (0.0, 3.6), (4.0, 7.2), ("W", "N")),
        ]
        doors = [Door("A", "B", (4.0, 1.8), 0), Door("B", "C", (6.0, 3.6), 1),
                 Door("C", "D", (4.0, 5.4), 0), Door("D", "A", (2.0, 3.6), 1)]
    mats = MaterialTable(rng)
    builder = MeshBuilder()
    pieces: list[Piece] = []
    hue0 = rng.random()
    for k, room in enumerate(rooms):
        hue = hue0 + k / len(rooms) + rng.uniform(-0.05, 0.05)
        room_doors = [d for d in doors if room.name in (d.a, d.b)]
        _shell(builder, mats, room, room_doors, hue, rng)
        furnisher = Furnisher(builder, mats, rng, room.name, room.kind, hue)
        furnisher.furnish(
            {side: room.wall_frame(side) for side in ("S", "E", "N", "W")},
            furnished=room.furnished,
            door_spans=_door_spans(room, room_doors),
            room_lo=np.asarray(room.lo), room_hi=np.asarray(room.hi),
            height=ROOM_HEIGHT,
        )
        pieces += furnisher.pieces
    for door in doors:
        _reveal(builder, mats, door, rng)
    vertices, triangles, material_ids = builder.build()
    return Scene(name, seed, vertices, triangles, material_ids, mats.materials,
                 tuple(rooms), tuple(doors), tuple(pieces))


def _room(name: str, kind: str, lo: tuple[float, float], hi: tuple[float, float],
          furnished: tuple[str, ...]) -> Room:
    return Room(name, kind, (lo[0] + WALL_HALF, lo[1] + WALL_HALF),
                (hi[0] - WALL_HALF, hi[1] - WALL_HALF), furnished)


def _door_spans(room: Room, doors: list[Door]) -> dict[str, list[tuple[float, float]]]:
    """Per wall side, the doorway intervals in that wall's along-coordinate."""
    spans: dict[str, list[tuple[float, float]]] = {s: [] for s in ("S", "E", "N", "W")}
    for door in doors:
        side = door.side_of(room)
        frame = room.wall_frame(side)
        centre = frame.along_of(np.asarray(door.center))
        spans[side].append((centre - 0.5 * door.width, centre + 0.5 * door.width))
    return spans


_WALL_PATTERNS = ("plaster", "stripes", "brick", "plaster", "dots")
_FLOOR_PATTERNS = {"living": "wood", "bedroom": "wood", "office": "tiles", "kitchen": "checker"}


def _shell(builder: MeshBuilder, mats: MaterialTable, room: Room, doors: list[Door],
           hue: float, rng: np.random.Generator) -> None:
    """Floor, ceiling and the four walls (with doorway openings) of one room."""
    (x0, y0), (x1, y1) = room.lo, room.hi
    floor_pattern = _FLOOR_PATTERNS.get(room.kind, "wood")
    floor_scale = {"wood": 0.18, "tiles": 0.4, "checker": 0.3}[floor_pattern]
    floor = mats.add(f"{room.name}/floor", floor_pattern,
                     hsv(hue + 0.08, rng.uniform(0.3, 0.6), rng.uniform(0.45, 0.7)),
                     hsv(hue + 0.5, rng.uniform(0.2, 0.5), rng.uniform(0.2, 0.4)), floor_scale)
    ceiling = mats.add(f"{room.name}/ceiling", "plaster", hsv(hue, 0.05, 0.92),
                       hsv(hue, 0.1, 0.75), 0.9)
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    builder.quad(np.c_[corners, np.zeros(4)], np.array([0, 0, 1.0]), floor)
    builder.quad(np.c_[corners, np.full(4, ROOM_HEIGHT)], np.array([0, 0, -1.0]), ceiling)
    patterns = list(rng.permutation(_WALL_PATTERNS))
    spans = _door_spans(room, doors)
    for k, side in enumerate(("S", "E", "N", "W")):
        pattern = patterns[k % len(patterns)]
        scale = {"plaster": 0.45, "stripes": rng.uniform(0.12, 0.3), "brick": 0.08,
                 "dots": rng.uniform(0.15, 0.3)}[pattern]
        wall = mats.add(f"{room.name}/wall_{side}", pattern,
                        hsv(hue + rng.uniform(-0.06, 0.06), rng.uniform(0.15, 0.45),
                            rng.uniform(0.7, 0.92)),
                        hsv(hue + rng.uniform(0.3, 0.7), rng.uniform(0.3, 0.7),
                            rng.uniform(0.35, 0.7)), scale)
        frame = room.wall_frame(side)
        edges = [0.0]
        for lo, hi in sorted(spans[side]):
            edges += [lo, hi]
        edges.append(frame.length)
        for k2 in range(0, len(edges), 2):  # full-height pieces between doorways
            if edges[k2 + 1] - edges[k2] > 1e-6:
                frame.wall_quad(builder, edges[k2], edges[k2 + 1], 0.0, ROOM_HEIGHT, wall)
        for k2 in range(1, len(edges) - 1, 2):  # above each doorway
            frame.wall_quad(builder, edges[k2], edges[k2 + 1], DOOR_HEIGHT, ROOM_HEIGHT, wall)


def _reveal(builder: MeshBuilder, mats: MaterialTable, door: Door,
            rng: np.random.Generator) -> None:
    """Jambs, lintel underside and threshold across the wall thickness of a doorway."""
    frame_mat = mats.add(f"door_{door.a}{door.b}/frame", "wood",
                         hsv(rng.uniform(0.05, 0.12), 0.5, rng.uniform(0.4, 0.6)),
                         hsv(0.08, 0.6, 0.25), 0.1)
    a = door.axis  # across the wall
    b = 1 - a  # along the wall
    c = np.asarray(door.center)
    t0, t1 = c[a] - WALL_HALF, c[a] + WALL_HALF
    for sign in (-1.0, 1.0):
        level = c[b] + sign * 0.5 * door.width
        pts = np.zeros((4, 3))
        pts[:, a] = [t0, t1, t1, t0]
        pts[:, b] = level
        pts[:, 2] = [0.0, 0.0, door.height, door.height]
        normal = np.zeros(3)
        normal[b] = -sign  # facing into the opening
        builder.quad(pts, normal, frame_mat)
    for z, nz in ((door.height, -1.0), (0.0, 1.0)):
        pts = np.zeros((4, 3))
        pts[:, a] = [t0, t1, t1, t0]
        pts[:, b] = [c[b] - 0.5 * door.width] * 2 + [c[b] + 0.5 * door.width] * 2
        pts[:, 2] = z
        builder.quad(pts, np.array([0.0, 0.0, nz]), frame_mat)
