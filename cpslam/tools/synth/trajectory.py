"""Hand-held camera paths through synthetic scenes.

A route is a list of waypoints (position, yaw, pitch); monotone cubic (PCHIP) curves through
them (wrapped for closed loops) give a smooth path, to which gentle height, pitch, yaw and
roll wobble is added. Frames are then placed at equal steps of the combined motion
sqrt((dp / v_max)^2 + (dtheta / w_max)^2), so that no frame moves more than v_max (1 cm) or
turns more than w_max (1 degree): fast where the camera only walks, slower where it turns.

Routes (world z up, camera looking along +x at yaw 0):
- room, open: agent i starts at a corner (then edge middles) of the room's free zone, walks
  to the middle looking at the north wall (where every agent's view overlaps), then tours the
  other corners;
- room, loop: an ellipse around the middle of the room, the view swinging left and right of
  the agent's wall (agent i faces the i-th most furnished one) and back; scaled down until
  it fits in the frame budget;
- apartment, open: agent i walks from its start room through a doorway into a shared room,
  meets the other agent entering it through another doorway, then looks around it;
- apartment, loop: from just before the doorway through it and back to the start pose,
  as deep into the shared room as the frames allow (or, for very few frames, an ellipse in
  the start room looking towards the doorway).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator

from cpslam.tools.synth.scene import CAMERA_Z, Room, Scene

V_MAX = 0.01  # metres per frame
W_MAX = np.radians(1.0)  # radians per frame
_FILL = 0.93  # frames use at most this fraction of both limits
_HEIGHT = 0.5 * (CAMERA_Z[0] + CAMERA_Z[1])
# Start room -> room it walks into; every room is entered from two sides.
_APARTMENT_PAIRS = (("A", "B"), ("C", "B"), ("D", "A"), ("B", "C"),
                    ("A", "D"), ("C", "D"), ("D", "C"), ("B", "A"))
MAX_AGENTS = len(_APARTMENT_PAIRS)


@dataclass(frozen=True)
class Route:
    """Waypoints: positions [K, 3], yaw [K] and pitch [K] in radians (yaw continuous)."""

    positions: np.ndarray
    yaw: np.ndarray
    pitch: np.ndarray
    closed: bool


def plan_trajectories(scene: Scene, agents: int, frames: int, loop: bool, seed: int
                      ) -> list[np.ndarray]:
    """Camera poses T_world_cam [frames, 4, 4] for each agent (OpenCV camera axes)."""
    if not 1 <= agents <= MAX_AGENTS:
        raise ValueError(f"agents must be between 1 and {MAX_AGENTS}, got {agents}")
    if frames < 2:
        raise ValueError(f"frames must be at least 2, got {frames}")
    poses = []
    for i in range(agents):
        rng = np.random.default_rng([seed, 7919, i])
        wobble = rng.uniform(0, 2 * np.pi, size=4)
        if loop:
            poses.append(_fit_closed(_loop_families(scene, i, agents), frames, wobble))
        else:
            route = (_room_tour(scene.rooms[0], i) if scene.name == "room"
                     else _apartment_walk(scene, i))
            poses.append(follow(route, frames, wobble))
    return poses


def follow(route: Route, frames: int, wobble: np.ndarray) -> np.ndarray:
    """Poses [frames, 4, 4] along `route`, at most V_MAX / W_MAX per frame.

    Open routes are walked at full speed from the start and cut where the frames run out (or
    walked slower when the route is short); closed routes must fit: the last frame is one
    step before the start.

    Raises:
        ValueError: for a closed route too long for `frames` (see `route_cost`).
    """
    curve, s_end = _splines(route)
    s_dense, cost = _cost_profile(curve, s_end, route.closed, wobble)
    if route.closed:
        step = cost[-1] / frames
        if step > _FILL:
            raise ValueError(f"closed route needs {cost[-1] / _FILL:.0f} frames, "
                             f"only {frames} given")
    else:
        step = min(_FILL, cost[-1] / (frames - 1))
    s = np.interp(step * np.arange(frames), cost, s_dense)
    return _poses(curve, s, s_end, route.closed, wobble)


def route_cost(route: Route, wobble: np.ndarray) -> float:
    """Length of a route in frames at the speed limits (both limits at once)."""
    curve, s_end = _splines(route)
    return float(_cost_profile(curve, s_end, route.closed, wobble)[1][-1]) / _FILL


def camera_rotation(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """R_world_cam [..., 3, 3] of an OpenCV camera (z forward, y down) in a z-up world.

    yaw about world z (0 = looking along +x), pitch up from the horizontal, roll about the
    optical axis.
    """
    yaw, pitch, roll = np.broadcast_arrays(yaw, pitch, roll)
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    forward = np.stack([cp * cy, cp * sy, sp], axis=-1)
    right = np.stack([sy, -cy, np.zeros_like(cy)], axis=-1)
    down = np.cross(forward, right)
    cr, sr = np.cos(roll)[..., None], np.sin(roll)[..., None]
    x_cam = cr * right + sr * down
    y_cam = -sr * right + cr * down
    return np.stack([x_cam, y_cam, forward], axis=-1)


# -- routes ------------------------------------------------------------------------------------

def _look(positions: np.ndarray, targets: np.ndarray, closed: bool) -> Route:
    delta = np.asarray(targets, float) - np.asarray(positions, float)
    yaw = np.unwrap(np.arctan2(delta[:, 1], delta[:, 0]))
    pitch = np.clip(np.arctan2(delta[:, 2], np.hypot(delta[:, 0], delta[:, 1])),
                    np.radians(-30), np.radians(20))
    if closed and abs(yaw[-1] - yaw[0]) > 1e-9:
        raise ValueError("closed route must end looking where it started")
    return Route(np.asarray(positions, float), yaw, pitch, closed)


def _wall_target(room: Room, p: np.ndarray, direction: np.ndarray, z: float = 1.0
                 ) -> np.ndarray:
    """Where the horizontal ray from p along `direction` meets the room's walls."""
    d = np.asarray(direction, float)[:2]
    d = d / np.linalg.norm(d)
    lo, hi = np.asarray(room.lo), np.asarray(room.hi)
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, (hi - p[:2]) / d, np.where(d < 0, (lo - p[:2]) / d, np.inf))
    xy = p[:2] + d * t.min()
    return np.array([xy[0], xy[1], z])


def _zone(room: Room) -> tuple[float, float, float, float]:
    """The free zone shrunk a little, so curve overshoot between waypoints stays inside."""
    x0, y0, x1, y1 = room.free_zone()
    return x0 + 0.1, y0 + 0.1, x1 - 0.1, y1 - 0.1


def _room_tour(room: Room, agent: int) -> Route:
    x0, y0, x1, y1 = _zone(room)
    c = np.array([0.5 * (x0 + x1), 0.5 * (y0 + y1), _HEIGHT])
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    middles = np.array([[c[0], y0], [x1, c[1]], [c[0], y1], [x0, c[1]]])
    starts = corners if agent < 4 else middles
    k = agent % 4
    ring = np.c_[np.roll(starts, -k, axis=0), np.full(4, _HEIGHT)]
    shared = np.array([c[0], room.hi[1], 1.0])  # the north wall, seen from the middle
    positions = [ring[0], c + 0.6 * (ring[0] - c), c, ring[2], ring[3], c]
    targets = [_wall_target(room, ring[0], c - ring[0]), shared, shared,
               _wall_target(room, ring[2], ring[2] - c), _wall_target(room, ring[3], ring[3] - c),
               shared]
    return _look(np.array(positions), np.array(targets), closed=False)


def _apartment_walk(scene: Scene, agent: int, sigma: float | None = None) -> Route:
    """From the start room through the doorway into the shared room (and back if sigma)."""
    start, goal = _APARTMENT_PAIRS[agent]
    room_s, room_t = scene.room(start), scene.room(goal)
    door = scene.door_between(start, goal)
    n = np.r_[door.normal_from(room_s), 0.0]
    d = np.array([door.center[0], door.center[1], _HEIGHT])
    meet = _meeting_point(scene, room_t)
    focus = room_t.focus()
    x0, y0, x1, y1 = _zone(room_t)
    corners = np.array([[x0, y0, _HEIGHT], [x1, y0, _HEIGHT], [x1, y1, _HEIGHT],
                        [x0, y1, _HEIGHT]])
    far = corners[np.argsort(-np.linalg.norm(corners[:, :2] - d[:2], axis=1))]
    if sigma is None:
        positions = [d - 0.75 * n, d - 0.4 * n, d, d + 0.55 * n, meet, far[0], far[1], meet]
        targets = [focus, focus, focus, focus, focus,
                   _wall_target(room_t, far[0], far[0] - meet),
                   _wall_target(room_t, far[1], far[1] - meet), focus]
        return _look(np.array(positions), np.array(targets), closed=False)
    # Out through the doorway (straight along its axis), into the shared room as far as
    # sigma says, a look aside, and back the same way to the start pose. On the doorway's
    # axis the jambs are 0.6 m away, so the start can be close to the wall.
    inner = d + 0.5 * n
    deep = inner + sigma * (meet - inner)
    aside = deep + sigma * 0.3 * (far[0] - meet)
    out = [d - 0.5 * n, d - 0.25 * n, d, d + 0.25 * n, inner, deep, aside,
           inner, d + 0.25 * n, d, d - 0.25 * n, d - 0.5 * n]
    wall = focus + sigma * (_wall_target(room_t, meet, far[0] - meet) - focus)
    targets = [focus] * 6 + [wall] + [focus] * 5
    return _look(np.array(out), np.array(targets), closed=True)


def _meeting_point(scene: Scene, room: Room) -> np.ndarray:
    """Between the room's doorways, inside its free zone: where agents entering meet."""
    doors = [np.asarray(dr.center) for dr in scene.doors if room.name in (dr.a, dr.b)]
    x0, y0, x1, y1 = _zone(room)
    xy = np.clip(np.mean(doors, axis=0), [x0, y0], [x1, y1])
    return np.array([xy[0], xy[1], _HEIGHT])


def _loop_families(scene: Scene, agent: int, agents: int) -> list[Callable[[float], Route]]:
    """Closed routes scaled by sigma in (0, 1], preferred family first."""
    if scene.name == "room":
        room = scene.rooms[0]
        phase = 2 * np.pi * agent / agents
        # Agent i faces the i-th most furnished wall (structure for tracking), starting on
        # its own side of the ellipse.
        walls = _walls_by_furniture(scene, room)
        side = walls[agent % len(walls)]
        frame = room.wall_frame(side)
        target = frame.point(0.5 * frame.length, 0.0)
        zone = np.array(_zone(room)).reshape(2, 2).mean(axis=0)
        base = float(np.arctan2(target[1] - zone[1], target[0] - zone[0]))
        return [lambda sigma: _ellipse_loop(room, base, phase, sigma)]
    start, goal = _APARTMENT_PAIRS[agent]
    room_s = scene.room(start)
    door = scene.door_between(start, goal)
    to_door = np.asarray(door.center) - room_s.center
    base = float(np.arctan2(to_door[1], to_door[0]))
    # Through the doorway and back when the frames allow it, else a loop in the start room
    # looking towards the doorway.
    return [lambda sigma: _apartment_walk(scene, agent, sigma),
            lambda sigma: _ellipse_loop(room_s, base, np.pi, sigma)]


def _walls_by_furniture(scene: Scene, room: Room) -> list[str]:
    """The room's walls, most pieces of furniture first (ties in S, E, N, W order)."""
    sides = ["S", "E", "N", "W"]
    count = {s: sum(p.room == room.name and p.side == s for p in scene.pieces) for s in sides}
    return sorted(sides, key=lambda s: -count[s])


def _ellipse_loop(room: Room, base_yaw: float, phase: float, sigma: float) -> Route:
    """An ellipse around the middle of the room's free zone, the view swinging about
    `base_yaw`; sigma scales the ellipse and the swing."""
    x0, y0, x1, y1 = _zone(room)
    c = np.array([0.5 * (x0 + x1), 0.5 * (y0 + y1)])
    axes = sigma * 0.5 * np.array([x1 - x0, y1 - y0])
    tau = np.linspace(0.0, 1.0, 17)
    angle = 2 * np.pi * tau + phase
    xy = c + axes * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    positions = np.c_[xy, np.full(len(tau), _HEIGHT)]
    yaw = base_yaw + sigma * np.radians(70) * np.sin(2 * np.pi * tau)
    pitch = np.radians(-12) + sigma * np.radians(5) * np.sin(4 * np.pi * tau)
    yaw[-1], pitch[-1] = yaw[0], pitch[0]
    return Route(positions, yaw, pitch, closed=True)


def _fit_closed(families: list[Callable[[float], Route]], frames: int, wobble: np.ndarray
                ) -> np.ndarray:
    """Walk the largest closed route (first family that fits, largest sigma) in `frames`."""
    for make in families:
        if route_cost(make(1.0), wobble) <= frames:
            return follow(make(1.0), frames, wobble)
        lo, hi = 1e-3, 1.0
        if route_cost(make(lo), wobble) > frames:
            continue
        for _ in range(30):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if route_cost(make(mid), wobble) <= frames else (lo, mid)
        return follow(make(lo), frames, wobble)
    raise ValueError(f"{frames} frames are too few for a loop; use at least 10")


# -- splines, wobble and timing ----------------------------------------------------------------

def _splines(route: Route) -> tuple[PchipInterpolator, float]:
    """Interpolant of (x, y, z, yaw, pitch) over a knot parameter in frames at full speed.

    PCHIP, not a cubic curve: it never overshoots, so between two waypoints each coordinate
    stays between their values and the path stays inside the box they span (what keeps the
    clearance). Closed routes are padded with wrapped waypoints, so that the curve is smooth
    through the start as well.
    """
    values = np.c_[route.positions, route.yaw, route.pitch]
    if route.closed:
        if not np.allclose(values[0], values[-1]):
            values = np.vstack([values, values[:1]])
        values[-1] = values[0]
    step = np.sqrt((np.linalg.norm(np.diff(values[:, :3], axis=0), axis=1) / V_MAX) ** 2
                   + (np.abs(np.diff(values[:, 3:], axis=0)).sum(axis=1) / W_MAX) ** 2)
    step = np.maximum(step, 1e-3)
    knots = np.r_[0.0, np.cumsum(step)]
    s_end = float(knots[-1])
    if route.closed:
        pad = 2
        values = np.vstack([values[-1 - pad:-1], values, values[1:1 + pad]])
        knots = np.r_[knots[-1 - pad:-1] - s_end, knots, knots[1:1 + pad] + s_end]
    return PchipInterpolator(knots, values, axis=0), s_end


def _wobble(s: np.ndarray, s_end: float, closed: bool, phases: np.ndarray) -> np.ndarray:
    """Hand-held wobble [len(s), 4]: dz (m), dyaw, dpitch, roll (rad); periods ~3-8 s."""
    periods = np.array([170.0, 230.0, 130.0, 200.0])
    amps = np.array([0.04, np.radians(3.0), np.radians(2.0), np.radians(1.5)])
    if closed:  # whole cycles, so the loop closes smoothly; small loops wobble less
        amps = amps * np.minimum(1.0, s_end / periods)
        periods = s_end / np.maximum(1, np.round(s_end / periods))
    return amps * np.sin(2 * np.pi * s[:, None] / periods + phases)


def _evaluate(curve: PchipInterpolator, s: np.ndarray, s_end: float, closed: bool,
              phases: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v = curve(s)
    w = _wobble(s, s_end, closed, phases)
    xyz = v[:, :3].copy()
    xyz[:, 2] = np.clip(xyz[:, 2] + w[:, 0], *CAMERA_Z)
    R = camera_rotation(v[:, 3] + w[:, 1], v[:, 4] + w[:, 2], w[:, 3])
    return xyz, R


def _cost_profile(curve: PchipInterpolator, s_end: float, closed: bool, phases: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Dense knot parameter and cumulative combined motion cost (frames at the limits)."""
    s = np.linspace(0.0, s_end, int(s_end * 12) + 50)
    xyz, R = _evaluate(curve, s, s_end, closed, phases)
    dp = np.linalg.norm(np.diff(xyz, axis=0), axis=1)
    cos = np.clip((np.einsum("nij,nij->n", R[:-1], R[1:]) - 1.0) / 2.0, -1.0, 1.0)
    dtheta = np.arccos(cos)
    return s, np.r_[0.0, np.cumsum(np.hypot(dp / V_MAX, dtheta / W_MAX))]


def _poses(curve: PchipInterpolator, s: np.ndarray, s_end: float, closed: bool,
           phases: np.ndarray) -> np.ndarray:
    xyz, R = _evaluate(curve, s, s_end, closed, phases)
    T = np.tile(np.eye(4), (len(s), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = xyz
    return T


def check_clearance(poses: list[np.ndarray], distance: Callable[[np.ndarray], np.ndarray],
                    minimum: float = 0.5) -> float:
    """Smallest camera-to-surface distance over all poses; raises if below `minimum`.

    Args:
        poses: per agent [N, 4, 4] T_world_cam.
        distance: maps world points [M, 3] to distances [M] (e.g. `Renderer.distance`).
    """
    worst = np.inf
    for agent, T in enumerate(poses):
        d = distance(T[:, :3, 3])
        worst = min(worst, float(d.min()))
        if d.min() < minimum:
            frame = int(np.argmin(d))
            raise RuntimeError(f"agent {agent} frame {frame}: camera at {T[frame, :3, 3]} is "
                               f"{d[frame]:.3f} m from the scene, below {minimum} m")
    return worst
