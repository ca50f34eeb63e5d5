"""Synthetic RGB-D scenes: geometry, textures, trajectories, rendering accuracy, output files."""

from __future__ import annotations

import hashlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from cpslam.common.camera import Intrinsics
from cpslam.common.datasets import open_sequence
from cpslam.common.geometry import transform_points
from cpslam.tools.synth.scene import CAMERA_Z, CLEARANCE, build_scene
from cpslam.tools.synth.texture import Material, shade
from cpslam.tools.synth.trajectory import plan_trajectories
from cpslam.tools.synth.writer import DEPTH_SCALE, generate

pytest.importorskip("open3d")


def _steps(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame translation (m) and rotation (deg) between consecutive poses."""
    dp = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    rel = np.einsum("nji,njk->nik", T[:-1, :3, :3], T[1:, :3, :3])
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)
    return dp, np.degrees(np.arccos(cos))


def _files_digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def renderers():
    from cpslam.tools.synth.render import Renderer, default_intrinsics

    return {name: Renderer(build_scene(name, 3), default_intrinsics(160, 120))
            for name in ("room", "apartment")}


@pytest.fixture(scope="module")
def collection(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "apt"
    generate(out, scene="apartment", agents=2, frames=5, width=64, height=48, seed=5)
    return out


# -- scene and texture ---------------------------------------------------------------------

def test_scene_is_seeded():
    a, b, c = build_scene("apartment", 1), build_scene("apartment", 1), build_scene("apartment", 2)
    assert np.array_equal(a.vertices, b.vertices) and a.materials == b.materials
    assert len(a.rooms) == 4 and len(a.doors) == 4
    assert not (a.vertices.shape == c.vertices.shape and np.allclose(a.vertices, c.vertices))
    assert a.material_ids.max() < len(a.materials)
    with pytest.raises(ValueError, match="unknown scene"):
        build_scene("castle")


def test_textures_vary_and_filter_to_mean():
    mat = Material("m", "checker", (0.9, 0.1, 0.1), (0.1, 0.1, 0.9), 0.2, seed=3)
    u = np.linspace(0.0, 2.0, 400)
    xyz = np.c_[u, np.zeros_like(u), np.full_like(u, 1.05)]  # a wall y = 0, normal -y
    normals = np.tile([0.0, -1.0, 0.0], (len(u), 1))
    sharp = shade([mat], np.zeros(len(u), int), xyz, normals, np.full(len(u), 1e-4))
    blurred = shade([mat], np.zeros(len(u), int), xyz, normals, np.full(len(u), 2.0))
    assert sharp[:, 0].std() > 0.2  # two colours
    assert blurred[:, 0].std() < 0.06  # a footprint of many periods gives the mean
    with pytest.raises(ValueError, match="unknown pattern"):
        Material("m", "marble", (0, 0, 0), (1, 1, 1), 1.0, 0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_free_zones_keep_clearance(seed):
    """Any camera in a room's free zone at camera height is CLEARANCE from every surface."""
    from cpslam.tools.synth.render import Renderer, default_intrinsics

    for name in ("room", "apartment"):
        scene = build_scene(name, seed)
        renderer = Renderer(scene, default_intrinsics(8, 8))
        for room in scene.rooms:
            x0, y0, x1, y1 = room.free_zone()
            grid = np.stack(np.meshgrid(np.linspace(x0, x1, 15), np.linspace(y0, y1, 15),
                                        CAMERA_Z), axis=-1).reshape(-1, 3)
            assert renderer.distance(grid).min() >= CLEARANCE - 1e-6, (name, room.name)


# -- trajectories ----------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["room", "apartment"])
@pytest.mark.parametrize("loop", [False, True])
def test_trajectory_speed_clearance_upright(name, loop, renderers):
    for T in plan_trajectories(renderers[name].scene, 2, 300, loop, seed=0):
        assert T.shape == (300, 4, 4)
        dp, dtheta = _steps(T)
        assert dp.max() < 0.015 and dtheta.max() < 1.5
        assert dp.mean() > 0.003  # it does move
        assert np.allclose(np.einsum("nij,nkj->nik", T[:, :3, :3], T[:, :3, :3]), np.eye(3),
                           atol=1e-9)
        # Upright: the camera's x axis stays near horizontal (small roll), y points down.
        assert np.abs(T[:, 2, 0]).max() < np.sin(np.radians(6))
        assert (T[:, 2, 1] < 0).all()
        assert renderers[name].distance(T[:, :3, 3]).min() >= CLEARANCE
        if loop:
            gap = np.linalg.norm(T[-1, :3, 3] - T[0, :3, 3])
            turn = _steps(np.stack([T[-1], T[0]]))[1][0]
            assert gap < 0.03 and turn < 2.0


@pytest.mark.parametrize("name", ["room", "apartment"])
def test_agents_start_apart_and_share_views(name, renderers):
    a, b = plan_trajectories(renderers[name].scene, 2, 300, loop=False, seed=0)
    assert np.linalg.norm(a[0, :3, 3] - b[0, :3, 3]) > 1.0
    dist = np.linalg.norm(a[:, None, :3, 3] - b[None, :, :3, 3], axis=-1)
    cos = np.einsum("ik,jk->ij", a[:, :3, 2], b[:, :3, 2])
    assert ((dist < 0.5) & (cos > np.cos(np.radians(30)))).any()


def test_trajectory_rejects_bad_arguments(renderers):
    with pytest.raises(ValueError, match="agents"):
        plan_trajectories(renderers["room"].scene, 9, 10, False, 0)
    with pytest.raises(ValueError, match="frames"):
        plan_trajectories(renderers["room"].scene, 1, 1, False, 0)


# -- rendering accuracy -----------------------------------------------------------------------

@pytest.mark.parametrize("name", ["room", "apartment"])
def test_depth_lands_on_mesh(name, renderers):
    renderer = renderers[name]
    K = renderer.intrinsics
    poses = plan_trajectories(renderer.scene, 1, 300, False, seed=0)[0]
    for T in poses[[0, 150, 299]]:
        image = renderer.render(T)
        assert (image.depth > 0).all()  # closed rooms: every ray hits
        assert image.rgb.reshape(-1, 3).std(axis=0).min() > 5  # textures, not flat colour
        quantised = np.round(image.depth * DEPTH_SCALE).astype(np.uint16) / DEPTH_SCALE
        # Float depth is exact up to float32 rays; the PNG's uint16 step is 0.15 mm.
        for depth, median, worst in ((image.depth, 1e-5, 1e-4),
                                     (quantised.astype(np.float32), 1e-4, 2.5e-4)):
            xyz_cam = K.backproject(depth).reshape(-1, 3)
            xyz_world = xyz_cam @ T[:3, :3].T + T[:3, 3]
            d = renderer.distance(xyz_world)
            assert np.median(d) < median and d.max() < worst


# -- output files ------------------------------------------------------------------------------

def test_outputs_replica_layout(collection):
    for i in range(2):
        folder = collection / f"agent_{i}"
        assert len(list((folder / "results").glob("frame*.png"))) == 5
        assert len(list((folder / "results").glob("depth*.png"))) == 5
        assert np.loadtxt(folder / "traj.txt").shape == (5, 16)
    depth = cv2.imread(str(collection / "agent_0/results/depth000000.png"), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and depth.shape == (48, 64) and depth.min() > 0
    import json

    summary = json.loads((collection / "scene.json").read_text())
    assert summary["seed"] == 5 and [a["frames"] for a in summary["agents"]] == [5, 5]


def test_same_seed_same_bytes_other_seed_differs(collection, tmp_path):
    again = tmp_path / "again"
    generate(again, scene="apartment", agents=2, frames=5, width=64, height=48, seed=5)
    assert _files_digest(again) == _files_digest(collection)
    other = tmp_path / "other"
    generate(other, scene="apartment", agents=2, frames=5, width=64, height=48, seed=6)
    a, b = _files_digest(collection), _files_digest(other)
    assert a.keys() == b.keys()
    assert a["mesh.ply"] != b["mesh.ply"]
    assert a["agent_0/results/frame000000.png"] != b["agent_0/results/frame000000.png"]
    with pytest.raises(FileExistsError, match="overwrite"):
        generate(other, scene="apartment", agents=1, frames=5, width=64, height=48)


def test_noise_changes_depth_and_adds_holes(tmp_path):
    kwargs = dict(scene="room", frames=3, width=64, height=48, seed=2)
    clean, noisy = tmp_path / "clean", tmp_path / "noisy"
    generate(clean, **kwargs)
    generate(noisy, noise=True, **kwargs)
    for f in range(3):
        name = f"agent_0/results/depth{f:06d}.png"
        a = cv2.imread(str(clean / name), cv2.IMREAD_UNCHANGED).astype(float)
        b = cv2.imread(str(noisy / name), cv2.IMREAD_UNCHANGED).astype(float)
        assert (a == 0).sum() == 0 and (b == 0).sum() > 0
        both = (a > 0) & (b > 0)
        err = np.abs(a - b)[both] / DEPTH_SCALE
        assert 0.0003 < np.median(err) < 0.02


def test_mesh_ply_matches_scene(collection):
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(collection / "mesh.ply"))
    assert mesh.has_vertex_colors() and len(mesh.triangles) > 1000
    xyz = np.asarray(mesh.vertices)
    lo, hi = build_scene("apartment", 5).bounds()
    assert np.allclose(xyz.min(axis=0), lo, atol=1e-4) and np.allclose(xyz.max(axis=0), hi,
                                                                          atol=1e-4)
    assert np.asarray(mesh.vertex_colors).std(axis=0).min() > 0.05


def test_loader_reads_output(collection):
    seq = open_sequence(collection / "agent_1")
    assert len(seq) == 5 and seq.has_gt
    assert seq.intrinsics == Intrinsics(51.2, 51.2, 31.5, 23.5, 64, 48)
    traj = np.loadtxt(collection / "agent_1/traj.txt").reshape(-1, 4, 4)
    assert np.allclose(seq.gt_poses(), traj, atol=1e-9)
    frame = seq[4]
    png = cv2.imread(str(collection / "agent_1/results/depth000004.png"), cv2.IMREAD_UNCHANGED)
    assert np.allclose(frame.depth, png / DEPTH_SCALE, atol=1e-6)
    bgr = cv2.imread(str(collection / "agent_1/results/frame000004.png"))
    assert np.array_equal(frame.rgb, bgr[:, :, ::-1])
    assert np.isclose(seq.timestamps[1] - seq.timestamps[0], 1 / 30)


def test_written_depth_lands_on_written_mesh(collection):
    """What a user gets on disk agrees with itself: PNG depth and traj.txt, read back through
    the dataset loader, back-project onto OUT/mesh.ply (not just onto the in-memory scene)."""
    import open3d as o3d

    from cpslam.tools.mesh import read_mesh

    mesh = o3d.t.geometry.TriangleMesh.from_legacy(read_mesh(collection / "mesh.ply"))
    surface = o3d.t.geometry.RaycastingScene()
    surface.add_triangles(mesh)
    for agent in ("agent_0", "agent_1"):
        seq = open_sequence(collection / agent)
        assert len(seq) == 5
        for frame in seq:
            assert (frame.depth > 0).all()  # noise-free closed rooms: every pixel has depth
            xyz_cam = seq.intrinsics.backproject(frame.depth).reshape(-1, 3)
            xyz_world = transform_points(frame.gt_pose, xyz_cam)
            d = surface.compute_distance(o3d.core.Tensor(xyz_world.astype(np.float32))).numpy()
            # The PNG's uint16 step is 0.15 mm, so rounding moves a point by 0.08 mm at most.
            assert np.median(d) < 5e-5 and d.max() < 1.5e-4, (agent, frame.index, d.max())


def test_cli_synth(tmp_path):
    import typer
    from typer.testing import CliRunner

    from cpslam.tools.synth.cli import synth

    app = typer.Typer()
    app.command()(synth)
    runner = CliRunner()
    help_text = runner.invoke(app, ["--help"]).output
    assert "Example" in help_text and "--agents" in help_text
    out = tmp_path / "cli"
    args = ["--out", str(out), "--num-frames", "3", "--width", "32", "--height", "24", "--loop"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "ms per frame" in result.output and str(out / "agent_0") in result.output
    again = runner.invoke(app, args)
    assert again.exit_code == 2 and "overwrite" in again.output
    assert runner.invoke(app, args + ["--overwrite"]).exit_code == 0
    bad = runner.invoke(app, ["--out", str(tmp_path / "x"), "--scene", "castle"])
    assert bad.exit_code == 2 and "scene" in bad.output
