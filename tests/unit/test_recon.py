"""Reconstruction metrics (`cpslam.tools.eval.recon`) and `cpslam eval recon`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import typer
from typer.testing import CliRunner

from cpslam.common.camera import Intrinsics
from cpslam.tools.eval import recon_cli
from cpslam.tools.eval.recon import (
    DEFAULT_SAMPLES,
    DEFAULT_THRESHOLD,
    Frustum,
    ReconResult,
    cull_to_frustum,
    depth_l1,
    evaluate_recon,
)
from cpslam.tools.eval.recon_cli import recon
from cpslam.tools.mesh import write_mesh

N = 40_000  # samples per mesh: enough for stable means, fast on two cores


def box(offset: float = 0.0) -> o3d.geometry.TriangleMesh:
    """A closed 1 m cube [0, 1]^3 (shifted by `offset` on every axis), finely triangulated."""
    mesh = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0).subdivide_midpoint(3)
    return mesh.translate(np.full(3, offset))


def half_box() -> o3d.geometry.TriangleMesh:
    """The cube without the triangles whose centroid has x < 0.5: half of its area."""
    mesh = box()
    centroid_x = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)][:, :, 0].mean(axis=1)
    mesh.remove_triangles_by_mask(centroid_x < 0.5)
    mesh.remove_unreferenced_vertices()
    return mesh


@pytest.mark.parametrize("method", ["points", "surface"])
def test_mesh_against_itself(method: str) -> None:
    result = evaluate_recon(box(), box(), samples=N, method=method)
    if method == "surface":
        assert result.accuracy < 1e-5 and result.completion < 1e-5
        assert result.accuracy_floor == 0.0
    else:
        # the floor of the papers' protocol: independent sample sets, so the mean distance
        # is the nearest-neighbour distance of a uniform 2-D scatter, 0.5 / sqrt(density):
        # 0.61 cm for 40k samples on 6 m^2 (measured 0.61 cm)
        floor = 0.5 / np.sqrt(N / 6.0)
        assert result.accuracy == pytest.approx(floor, rel=0.05)
        assert result.completion == pytest.approx(floor, rel=0.05)
        assert result.accuracy_floor == pytest.approx(floor, rel=1e-6)
        assert result.completion_floor == pytest.approx(floor, rel=1e-6)
    assert result.completion_ratio == 1.0 and result.precision == 1.0
    assert result.f_score == 1.0


@pytest.mark.parametrize("method", ["points", "surface"])
def test_known_offset(method: str) -> None:
    # every face moves 3 cm along its normal (plus sideways), so distances are 3 cm except
    # within 3 cm of an edge
    result = evaluate_recon(box(0.03), box(), samples=N, method=method)
    assert result.accuracy == pytest.approx(0.03, abs=0.003)
    assert result.completion == pytest.approx(0.03, abs=0.003)
    assert result.completion_ratio > 0.95
    far = evaluate_recon(box(0.06), box(), samples=N, method=method)
    assert far.completion_ratio < 0.1 and far.precision < 0.1


def test_completion_drops_when_half_is_missing() -> None:
    full = evaluate_recon(box(), box(), samples=N, method="surface")
    half = evaluate_recon(half_box(), box(), samples=N, method="surface")
    assert full.completion_ratio == 1.0
    # half the area plus a 5 cm band next to what is left
    assert 0.5 < half.completion_ratio < 0.6
    assert half.completion > 0.1
    assert half.accuracy < 1e-5 and half.precision == 1.0  # what is there is right


def test_seeded_and_validated() -> None:
    a = evaluate_recon(box(0.01), box(), samples=5000, seed=3)
    b = evaluate_recon(box(0.01), box(), samples=5000, seed=3)
    c = evaluate_recon(box(0.01), box(), samples=5000, seed=4)
    assert a.accuracy == b.accuracy and a.accuracy != c.accuracy
    with pytest.raises(ValueError, match="method 'chamfer'"):
        evaluate_recon(box(), box(), samples=10, method="chamfer")
    with pytest.raises(ValueError, match="must be > 0"):
        evaluate_recon(box(), box(), samples=10, threshold=0.0)


def test_to_dict_units() -> None:
    result = evaluate_recon(box(0.03), box(), samples=5000, method="surface")
    record = result.to_dict()
    json.dumps(record)
    assert record["accuracy_cm"] == pytest.approx(100 * record["accuracy_m"])
    assert record["completion_ratio_pct"] == pytest.approx(100 * result.completion_ratio)
    assert record["threshold_m"] == DEFAULT_THRESHOLD and record["method"] == "surface"
    assert record["f_score"] == pytest.approx(result.f_score)
    assert record["accuracy_floor_cm"] == 0.0  # surface distances have no sampling floor


# A camera at the origin looking along +z (identity pose) at the plane z = 2.
INTR = Intrinsics(100.0, 100.0, 49.5, 39.5, 100, 80)


def test_frustum_visibility() -> None:
    xyz = np.array(
        [
            [0.0, 0.0, 2.0],  # centre of the image
            [0.0, 0.0, -2.0],  # behind the camera
            [5.0, 0.0, 2.0],  # right of the image (u = 300)
            [0.0, 0.0, 7.0],  # beyond depth_max
            [0.98, 0.0, 2.0],  # u = 98.5: last column
            [1.0, 0.0, 2.0],  # u = 99.5: just outside
            [0.0, 0.0, 2.04],  # behind the observed plane, within the tolerance
            [0.0, 0.0, 2.5],  # hidden behind the plane
        ]
    )
    seen = Frustum(np.eye(4), INTR, depth_max=6.0).visible(xyz)
    np.testing.assert_array_equal(seen, [1, 0, 0, 0, 1, 0, 1, 1])
    plane = np.full((80, 100), 2.0, np.float32)
    seen = Frustum(np.eye(4)[None], INTR, depths=[plane]).visible(xyz)
    np.testing.assert_array_equal(seen, [1, 0, 0, 0, 1, 0, 1, 0])
    # the camera turned around sees the point behind; a NaN pose (no ground truth) is skipped
    turned = np.diag([-1.0, 1.0, -1.0, 1.0])
    poses = np.stack([np.full((4, 4), np.nan), turned])
    assert Frustum(poses, INTR).visible(xyz)[1]
    # no reading at the pixel: not seen
    holes = plane.copy()
    holes[40, 50] = 0.0
    assert not Frustum(np.eye(4), INTR, depths=[holes]).visible(xyz[:1])[0]


def test_frustum_errors() -> None:
    with pytest.raises(ValueError, match=r"\[N, 4, 4\]"):
        Frustum(np.eye(3), INTR)
    with pytest.raises(ValueError, match="2 depth images for 1 poses"):
        Frustum(np.eye(4), INTR, depths=[np.zeros((80, 100))] * 2)
    with pytest.raises(ValueError, match="depth image 0 has shape"):
        Frustum(np.eye(4), INTR, depths=[np.zeros((8, 10))]).visible(np.ones((1, 3)))


def test_cull_mesh_and_points() -> None:
    # camera 3 m in front of the cube's z = 0 face... seen from below, looking up (+z)
    T = np.eye(4)
    T[:3, 3] = [0.5, 0.5, -3.0]
    mesh = box()
    culled = cull_to_frustum(mesh, T[None], INTR, depth_max=3.5)
    assert 0 < len(culled.triangles) < len(mesh.triangles)
    assert np.asarray(culled.vertices)[:, 2].max() <= 0.5 + 1e-9  # z - (-3) <= 3.5
    assert len(mesh.triangles) == len(box().triangles)  # the input is untouched
    points = np.array([[0.5, 0.5, 0.0], [0.5, 0.5, 1.0]])
    np.testing.assert_array_equal(cull_to_frustum(points, T, INTR, 3.5), points[:1])


def test_culling_scores_only_what_was_seen() -> None:
    T = np.eye(4)
    T[:3, 3] = [0.5, 0.5, -3.0]
    frustum = Frustum(T, INTR, depths=[np.full((80, 100), 3.0, np.float32)])
    # only the bottom face (z = 0) is seen; the half box lacks part of it
    whole = evaluate_recon(half_box(), box(), samples=N, method="surface")
    seen = evaluate_recon(half_box(), box(), samples=N, method="surface", frustum=frustum)
    assert seen.culled and seen.n_gt < N / 5 and seen.n_est < N / 5
    assert seen.completion_ratio == pytest.approx(whole.completion_ratio, abs=0.05)
    away = np.eye(4)
    away[:3, 3] = [0.5, 0.5, 5.0]
    with pytest.raises(ValueError, match="no reconstructed sample lies inside"):
        evaluate_recon(box(), box(), samples=1000, frustum=Frustum(away, INTR, depth_max=1.0))


def test_depth_l1() -> None:
    rng = np.random.default_rng(0)
    gt = rng.uniform(0.5, 4.0, (3, 20, 30)).astype(np.float32)
    assert depth_l1(gt, gt) == 0.0
    assert depth_l1(gt + 0.02, gt) == pytest.approx(0.02, abs=1e-6)
    assert depth_l1(gt[0] - 0.05, gt[0]) == pytest.approx(0.05, abs=1e-6)  # one [H, W] pair
    # pixels invalid in either image do not count
    rendered = gt + 0.01
    rendered[:, :10] = 0.0
    gt_holes = gt.copy()
    gt_holes[:, :, :5] = np.nan
    rendered[:, 15:, :] += 100.0
    gt_holes[:, 15:, :] = 0.0
    assert depth_l1(rendered, gt_holes) == pytest.approx(0.01, abs=1e-6)
    # every frame weighs the same, whatever its number of valid pixels
    a = np.full((4, 4), 1.0)
    b = np.zeros((4, 4))
    b[0, 0] = 1.0
    assert depth_l1([a + 0.01, b + 0.03 * (b > 0)], [a, b]) == pytest.approx(0.02)
    # a frame with nothing in common is skipped
    assert depth_l1([a + 0.01, np.zeros((4, 4))], [a, a]) == pytest.approx(0.01)


def test_depth_l1_errors() -> None:
    a = np.ones((4, 4))
    with pytest.raises(ValueError, match="2 rendered depth images but 1 gt"):
        depth_l1([a, a], [a])
    with pytest.raises(ValueError, match=r"frame 1: rendered \(4, 4\) and gt \(4, 5\)"):
        depth_l1([a, a], [a, np.ones((4, 5))])
    with pytest.raises(ValueError, match="no pixel is valid"):
        depth_l1([np.zeros((4, 4))], [a])


def test_cli_defaults_mirror_the_library() -> None:
    assert recon_cli._DEFAULT_SAMPLES == DEFAULT_SAMPLES
    assert recon_cli._DEFAULT_THRESHOLD == DEFAULT_THRESHOLD


@pytest.fixture
def app() -> typer.Typer:
    app = typer.Typer()
    app.command()(recon)

    @app.command()
    def other() -> None:  # a second command keeps `recon` a named subcommand, as in cpslam
        pass

    return app


def test_cli_happy_path(tmp_path: Path, app: typer.Typer) -> None:
    gt, est = write_mesh(tmp_path / "gt.ply", box()), write_mesh(tmp_path / "est.ply", box(0.03))
    out = tmp_path / "out" / "recon.json"
    args = ["recon", "--gt", str(gt), "--est", str(est), "--samples", "20000", "--sample-seed", "1"]
    result = CliRunner().invoke(app, [*args, "--method", "surface", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "accuracy" in result.output and "cm" in result.output
    assert "sampling floor" not in result.output  # surface method
    record = json.loads(out.read_text())
    assert record["gt"] == str(gt) and record["samples"] == 20000 and record["seed"] == 1
    assert record["accuracy_cm"] == pytest.approx(3.0, abs=0.3)
    assert record["cull_to"] is None


def test_cli_cull_to_dataset(tmp_path: Path, app: typer.Typer) -> None:
    from cpslam.tools.synth import generate

    generate(tmp_path / "syn", frames=3, width=64, height=48, seed=1)
    gt = tmp_path / "syn" / "mesh.ply"
    args = [
        "recon",
        "--gt",
        str(gt),
        "--est",
        str(gt),
        "--samples",
        "5000",
        "--occlusion",
        "--cull-to",
        str(tmp_path / "syn" / "agent_0"),
        "--frames",
        "0:3",
        "--out",
        str(tmp_path / "r.json"),
    ]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    record = json.loads((tmp_path / "r.json").read_text())
    assert record["culled"] and 0 < record["n_gt"] < 5000
    assert record["cull_to"].endswith("agent_0")
    assert "sampling floor" in result.output  # points method


def test_cli_errors_name_the_file(tmp_path: Path, app: typer.Typer) -> None:
    gt = write_mesh(tmp_path / "gt.ply", box())
    missing = tmp_path / "missing.ply"
    result = CliRunner().invoke(app, ["recon", "--gt", str(gt), "--est", str(missing)])
    assert result.exit_code == 2 and "missing.ply" in result.output
    junk = tmp_path / "junk.ply"
    junk.write_text("ply?\n")
    result = CliRunner().invoke(app, ["recon", "--gt", str(junk), "--est", str(gt)])
    assert result.exit_code == 2 and "junk.ply" in result.output
    result = CliRunner().invoke(
        app, ["recon", "--gt", str(gt), "--est", str(gt), "--cull-to", str(tmp_path / "nodata")]
    )
    assert result.exit_code == 2 and "nodata" in result.output


def test_result_f_score_zero() -> None:
    result = ReconResult(1.0, 1.0, 0.0, 0.0, 0.05, "points", 10, 0, 10, 10, False, 0.0)
    assert result.f_score == 0.0
