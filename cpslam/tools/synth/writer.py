"""Generate a synthetic RGB-D collection on disk in the Replica layout.

    OUT/scene.json                   what was generated (scene, seed, arguments, rooms, agents)
    OUT/mesh.ply                     ground-truth mesh, vertex colours from the textures
    OUT/agent_<i>/results/frame%06d.png   RGB (lossless)
    OUT/agent_<i>/results/depth%06d.png   uint16 depth, 6553.5 units per metre, 0 = invalid
    OUT/agent_<i>/traj.txt           one row-major 4x4 T_world_cam per line (ground truth)
    OUT/agent_<i>/camera.yaml        fx, fy, cx, cy, width, height, depth_scale, fps

Every file is a function of the arguments alone (no time stamps, no absolute paths), so the
same arguments give byte-identical output.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml

from cpslam.common.logs import progress
from cpslam.common.rundir import SCHEMA_VERSION
from cpslam.tools.synth.render import Renderer, default_intrinsics, kinect_noise
from cpslam.tools.synth.scene import SCENES, Scene, build_scene
from cpslam.tools.synth.texture import shade
from cpslam.tools.synth.trajectory import MAX_AGENTS, check_clearance, plan_trajectories

logger = logging.getLogger(__name__)

DEPTH_SCALE = 6553.5
MESH_CELL = 0.1  # metres: mesh.ply resolution of the texture colours


@dataclass
class SynthResult:
    """Where the outputs went and how long rendering took."""

    out: Path
    agent_dirs: list[Path]
    mesh_path: Path
    scene_json: Path
    frames_per_agent: int
    seconds_per_frame: float  # ray casting + shading + noise, mean over all frames
    total_seconds: float
    min_clearance: float  # smallest camera-to-surface distance over all frames (m)
    timings: dict[str, float] = field(default_factory=dict)


def generate(
    out: Path,
    scene: str = "room",
    agents: int = 1,
    frames: int = 300,
    width: int = 320,
    height: int = 240,
    seed: int = 0,
    noise: bool = False,
    loop: bool = False,
    fps: float = 30.0,
    overwrite: bool = False,
    show_progress: bool = False,
) -> SynthResult:
    """Render a synthetic collection (one sequence per agent) into `out`.

    Args:
        out: output folder (created).
        scene: "room" (one furnished room) or "apartment" (four rooms with doorways).
        agents: number of sequences, 1 to 8; they start apart and share views.
        frames: frames per agent.
        width, height: image size; fx = fy = 0.8 width.
        seed: chooses furniture, textures, wobble and depth noise.
        noise: Kinect-like depth noise and holes (see `render.kinect_noise`).
        loop: closed trajectories that return to their start pose.
        fps: frame rate written to camera.yaml (trajectories assume 30 Hz hand-held speeds).
        overwrite: replace an earlier collection in `out`.
        show_progress: draw a progress bar.

    Raises:
        ValueError: for an argument out of range, naming it.
        FileExistsError: if `out` already holds a collection and `overwrite` is False.
    """
    t_start = time.perf_counter()
    _check_args(scene, agents, frames, width, height, fps)
    out = Path(out)
    _prepare(out, overwrite)
    world = build_scene(scene, seed)
    intrinsics = default_intrinsics(width, height)
    renderer = Renderer(world, intrinsics)
    poses = plan_trajectories(world, agents, frames, loop, seed)
    clearance = check_clearance(poses, renderer.distance)
    t_setup = time.perf_counter() - t_start

    agent_dirs = [out / f"agent_{i}" for i in range(agents)]
    camera = {**intrinsics.to_dict(), "depth_scale": DEPTH_SCALE, "fps": float(fps)}
    for folder, T in zip(agent_dirs, poses, strict=True):
        (folder / "results").mkdir(parents=True, exist_ok=True)
        (folder / "camera.yaml").write_text(yaml.safe_dump(camera, sort_keys=False))
        np.savetxt(folder / "traj.txt", T.reshape(len(T), 16), fmt="%.18e")

    render_seconds = 0.0
    jobs = [(a, f) for a in range(agents) for f in range(frames)]
    for a, f in progress(jobs, desc=f"render {scene}", disable=not show_progress):
        t0 = time.perf_counter()
        image = renderer.render(poses[a][f])
        depth = image.depth
        if noise:
            depth = kinect_noise(depth, image.cos_incidence, np.random.default_rng([seed, a, f]))
        render_seconds += time.perf_counter() - t0
        write_frame(agent_dirs[a] / "results", f, image.rgb, depth)

    t0 = time.perf_counter()
    mesh_path = out / "mesh.ply"
    write_mesh(mesh_path, world)
    t_mesh = time.perf_counter() - t0
    scene_json = out / "scene.json"
    args = {"scene": scene, "agents": agents, "frames": frames, "width": width,
            "height": height, "seed": seed, "noise": noise, "loop": loop, "fps": float(fps)}
    scene_json.write_text(json.dumps({"schema_version": SCHEMA_VERSION,
                                      **_summary(world, args, camera, poses)}, indent=2) + "\n")
    total = time.perf_counter() - t_start
    per_frame = render_seconds / max(1, len(jobs))
    logger.info("wrote %d agent(s) x %d frames to %s (%.1f ms per frame)", agents, frames, out,
                1000 * per_frame)
    return SynthResult(out, agent_dirs, mesh_path, scene_json, frames, per_frame, total,
                       clearance, {"setup": t_setup, "render": render_seconds, "mesh": t_mesh})


def write_frame(results: Path, index: int, rgb: np.ndarray, depth: np.ndarray) -> None:
    """Write results/frame%06d.png (RGB) and results/depth%06d.png (uint16 at DEPTH_SCALE).

    Depth beyond what uint16 holds at this scale (10 m) is written as 0 (invalid).
    """
    units = np.round(depth.astype(np.float64) * DEPTH_SCALE)
    units[(units > 65535) | ~np.isfinite(units)] = 0
    frame_path = results / f"frame{index:06d}.png"
    depth_path = results / f"depth{index:06d}.png"
    png = [cv2.IMWRITE_PNG_COMPRESSION, 3]
    if not cv2.imwrite(str(frame_path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), png):
        raise OSError(f"{frame_path}: cv2.imwrite failed")
    if not cv2.imwrite(str(depth_path), units.astype(np.uint16), png):
        raise OSError(f"{depth_path}: cv2.imwrite failed")


def colored_mesh(scene: Scene, cell: float = MESH_CELL
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scene mesh subdivided to about `cell` metres, coloured by its textures.

    Returns:
        vertices [V, 3] float64, triangles [T, 3] int64, colours [V, 3] uint8.
    """
    v = scene.vertices[scene.triangles]  # [T, 3, 3]
    edges = np.linalg.norm(v - np.roll(v, 1, axis=1), axis=2).max(axis=1)
    levels = np.clip(np.ceil(edges / cell), 1, 200).astype(int)
    normals = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    out_v, out_t, out_c = [], [], []
    count = 0
    for n in np.unique(levels):
        sel = np.flatnonzero(levels == n)
        bary, sub = _lattice(int(n))
        xyz = np.einsum("pk,tkc->tpc", bary, v[sel]).reshape(-1, 3)
        mats = np.repeat(scene.material_ids[sel], len(bary))
        nrm = np.repeat(normals[sel], len(bary), axis=0)
        rgb = shade(scene.materials, mats, xyz, nrm, np.full(len(xyz), cell))
        offsets = count + len(bary) * np.arange(len(sel))
        out_t.append((sub[None, :, :] + offsets[:, None, None]).reshape(-1, 3))
        out_v.append(xyz)
        out_c.append(np.round(rgb * 255).astype(np.uint8))
        count += len(xyz)
    return np.concatenate(out_v), np.concatenate(out_t), np.concatenate(out_c)


def write_mesh(path: Path, scene: Scene, cell: float = MESH_CELL) -> None:
    """Binary little-endian PLY of `colored_mesh` (float xyz, uchar rgb, int faces)."""
    vertices, triangles, colours = colored_mesh(scene, cell)
    vert = np.empty(len(vertices), dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    vert["xyz"], vert["rgb"] = vertices, colours
    face = np.empty(len(triangles), dtype=[("n", "u1"), ("idx", "<i4", 3)])
    face["n"], face["idx"] = 3, triangles
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"comment cpslam synthetic scene {scene.name} seed {scene.seed}, z up, metres\n"
        f"element vertex {len(vert)}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {len(face)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(vert.tobytes())
        fh.write(face.tobytes())


def _lattice(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric weights [P, 3] of a triangle split n times per edge, and the n^2
    sub-triangles [n^2, 3] indexing them (same winding as the triangle)."""
    index = {}
    bary = []
    for i in range(n + 1):
        for j in range(n + 1 - i):
            index[i, j] = len(bary)
            bary.append(((n - i - j) / n, i / n, j / n))
    sub = []
    for i in range(n):
        for j in range(n - i):
            sub.append((index[i, j], index[i + 1, j], index[i, j + 1]))
            if i + j < n - 1:
                sub.append((index[i + 1, j], index[i + 1, j + 1], index[i, j + 1]))
    return np.asarray(bary), np.asarray(sub, dtype=np.int64)


def _summary(world: Scene, args: dict, camera: dict, poses: list[np.ndarray]) -> dict:
    def r(x: float) -> float:
        return round(float(x), 4)

    return {
        "generator": "cpslam.tools.synth",
        "format_version": 1,
        "scene": world.name,
        "seed": world.seed,
        "args": args,
        "world_frame": "metres, z up, floor at z = 0; poses are T_world_cam with OpenCV "
                       "camera axes (x right, y down, z forward)",
        "camera": camera,
        "mesh": {"file": "mesh.ply", "source_triangles": int(len(world.triangles)),
                 "materials": len(world.materials), "cell_m": MESH_CELL},
        "rooms": [{"name": rm.name, "kind": rm.kind, "lo": [r(x) for x in rm.lo],
                   "hi": [r(x) for x in rm.hi], "furnished_walls": list(rm.furnished)}
                  for rm in world.rooms],
        "doors": [{"rooms": [d.a, d.b], "center": [r(x) for x in d.center],
                   "width": d.width, "height": d.height} for d in world.doors],
        "agents": [{"folder": f"agent_{i}", "frames": int(len(T)),
                    "path_length_m": r(np.linalg.norm(np.diff(T[:, :3, 3], axis=0),
                                                      axis=1).sum()),
                    "start": [r(x) for x in T[0, :3, 3]]} for i, T in enumerate(poses)],
    }


def _check_args(scene: str, agents: int, frames: int, width: int, height: int,
                fps: float) -> None:
    if scene not in SCENES:
        raise ValueError(f"scene: expected one of {', '.join(SCENES)}, got {scene!r}")
    if not 1 <= agents <= MAX_AGENTS:
        raise ValueError(f"agents: expected 1 to {MAX_AGENTS}, got {agents}")
    if frames < 2:
        raise ValueError(f"frames: expected at least 2, got {frames}")
    if width < 8 or height < 8:
        raise ValueError(f"width/height: expected at least 8 pixels, got {width}x{height}")
    if not fps > 0:
        raise ValueError(f"fps: expected > 0, got {fps}")


def _prepare(out: Path, overwrite: bool) -> None:
    """Create `out`; refuse (or clear, with `overwrite`) an earlier collection in it."""
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out}: exists and is not a folder")
    ours = sorted(out.glob("agent_*")) + [p for p in (out / "scene.json", out / "mesh.ply")
                                          if p.exists()]
    if ours and not overwrite:
        raise FileExistsError(f"{out}: already holds a synthetic collection "
                              f"({ours[0].name}); pass overwrite (--overwrite) to replace it")
    for path in ours:
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink()
    out.mkdir(parents=True, exist_ok=True)
