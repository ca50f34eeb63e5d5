"""Dataset loaders on tiny fixtures of each layout written here with cv2."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from cpslam.common.camera import Intrinsics
from cpslam.common.datasets import (
    DatasetError,
    RGBDFrame,
    detect_format,
    open_sequence,
    parse_frames,
)
from cpslam.common.datasets.cli import info
from cpslam.common.datasets.tum import associate

W, H = 32, 24
N = 5


def make_rgb(i: int, w: int = W, h: int = H) -> np.ndarray:
    """A colour image whose channels differ, so a BGR/RGB swap shows."""
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[..., 0] = 200
    rgb[..., 1] = np.arange(w, dtype=np.uint8)[None, :] * 4
    rgb[..., 2] = 10 + i
    return rgb


def make_depth(i: int, w: int = W, h: int = H) -> np.ndarray:
    """Depth in metres: 1 m + 0.1 m per frame + a ramp; a hole at (0, 0)."""
    depth = 1.0 + 0.1 * i + np.linspace(0.0, 1.0, w, dtype=np.float32)[None, :].repeat(h, 0)
    depth[0, 0] = 0.0
    return depth.astype(np.float32)


def make_pose(i: int) -> np.ndarray:
    a = 0.1 * i
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:3, 3] = [0.1 * i, -0.05 * i, 0.02 * i]
    return T


def write_rgb(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def write_depth(path: Path, depth_m: np.ndarray, scale: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.round(depth_m * scale).astype(np.uint16))


def write_camera_yaml(root: Path, text: str = "") -> None:
    (root / "camera.yaml").write_text(
        text or f"fx: 30.0\nfy: 31.0\ncx: 15.5\ncy: 11.5\nwidth: {W}\nheight: {H}\nfps: 10\n"
    )


@pytest.fixture
def replica_root(tmp_path: Path) -> Path:
    root = tmp_path / "room0"
    for i in range(N):
        write_rgb(root / "results" / f"frame{i:06d}.png", make_rgb(i))
        write_depth(root / "results" / f"depth{i:06d}.png", make_depth(i), 6553.5)
    lines = [" ".join(f"{v:.17g}" for v in make_pose(i).ravel()) for i in range(N)]
    (root / "traj.txt").write_text("\n".join(lines) + "\n")
    write_camera_yaml(root)
    return root


@pytest.fixture
def sevenscenes_root(tmp_path: Path) -> Path:
    root = tmp_path / "seq-01"
    for i in range(N):
        write_rgb(root / f"frame-{i:06d}.color.png", make_rgb(i))
        depth = make_depth(i)
        raw = np.round(depth * 1000).astype(np.uint16)
        raw[1, 1] = 65535  # 7-Scenes' other "no reading" value
        root.mkdir(exist_ok=True)
        cv2.imwrite(str(root / f"frame-{i:06d}.depth.png"), raw)
        np.savetxt(root / f"frame-{i:06d}.pose.txt", make_pose(i))
    return root


@pytest.fixture
def scannet_root(tmp_path: Path) -> Path:
    root = tmp_path / "scene0000_00"
    for i in range(N):
        write_rgb(root / "color" / f"{i}.jpg", make_rgb(i, 2 * W, 2 * H))
        write_depth(root / "depth" / f"{i}.png", make_depth(i), 1000.0)
        (root / "pose").mkdir(exist_ok=True)
        pose = make_pose(i) if i != 2 else np.full((4, 4), -np.inf)
        np.savetxt(root / "pose" / f"{i}.txt", pose)
    (root / "intrinsic").mkdir()
    K = np.eye(4)
    K[0, 0], K[1, 1], K[0, 2], K[1, 2] = 28.0, 29.0, 15.0, 11.0
    np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", K)
    return root


TUM_T0 = 1305031102.0


@pytest.fixture
def tum_root(tmp_path: Path) -> Path:
    """Six colour images at 30 Hz; the 4th has no depth near it; ground truth ends early."""
    root = tmp_path / "rgbd_dataset_freiburg1_tiny"
    rgb_lines, depth_lines = ["# color images", "# timestamp filename"], ["# depth maps"]
    for i in range(6):
        t = TUM_T0 + i / 30.0
        write_rgb(root / "rgb" / f"{t:.6f}.png", make_rgb(i))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        if i == 3:
            continue
        td = t + 0.008
        write_depth(root / "depth" / f"{td:.6f}.png", make_depth(i), 5000.0)
        depth_lines.append(f"{td:.6f} depth/{td:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    gt_lines = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    for k in range(12):  # 100 Hz up to ~0.11 s: covers frames 0..3 only
        t = TUM_T0 + k / 100.0 + 0.001
        gt_lines.append(f"{t:.4f} {0.01 * k} 0 0 0 0 {np.sin(0.01 * k):.9f} {np.cos(0.01 * k):.9f}")
    (root / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    return root


# -- loading each format ------------------------------------------------------------------


def test_replica_loads_frames_poses_and_sidecar(replica_root: Path) -> None:
    seq = open_sequence(replica_root)
    assert seq.format == "replica" and len(seq) == N
    assert seq.intrinsics == Intrinsics(30.0, 31.0, 15.5, 11.5, W, H)
    assert seq.fps == 10.0
    np.testing.assert_allclose(seq.timestamps, np.arange(N) / 10.0)
    frame = seq[2]
    assert isinstance(frame, RGBDFrame) and frame.index == 2
    assert frame.rgb.dtype == np.uint8 and frame.rgb.shape == (H, W, 3)
    np.testing.assert_array_equal(frame.rgb, make_rgb(2))  # RGB order, lossless PNG
    assert frame.depth.dtype == np.float32 and frame.depth.shape == (H, W)
    np.testing.assert_allclose(frame.depth, make_depth(2), atol=1.0 / 6553.5)
    assert frame.depth[0, 0] == 0.0
    np.testing.assert_allclose(frame.gt_pose, make_pose(2), atol=1e-12)
    np.testing.assert_allclose(seq.gt_poses(), np.stack([make_pose(i) for i in range(N)]))


def test_replica_default_camera_only_at_replica_size(tmp_path: Path) -> None:
    root = tmp_path / "office0"
    write_rgb(root / "results" / "frame000000.jpg", make_rgb(0, 1200, 680))
    write_depth(root / "results" / "depth000000.png", make_depth(0, 1200, 680), 6553.5)
    seq = open_sequence(root)
    assert seq.intrinsics == Intrinsics(600.0, 600.0, 599.5, 339.5, 1200, 680)
    assert not seq.has_gt and seq.gt_poses() is None
    assert seq[0].gt_pose is None and seq[0].rgb.shape == (680, 1200, 3)


def test_replica_without_camera_at_other_size_names_what_is_missing(
    replica_root: Path,
) -> None:
    (replica_root / "camera.yaml").unlink()
    with pytest.raises(DatasetError, match="camera.yaml") as e:
        open_sequence(replica_root)
    assert str(replica_root) in str(e.value) and "fx" in str(e.value) and "32x24" in str(e.value)
    # An explicit override is enough on its own.
    camera = Intrinsics(20.0, 20.0, 16.0, 12.0, W, H)
    assert open_sequence(replica_root, intrinsics=camera).intrinsics == camera


def test_sevenscenes_published_camera_invalid_depth_and_pose_files(
    sevenscenes_root: Path,
) -> None:
    seq = open_sequence(sevenscenes_root)
    assert seq.format == "7scenes"
    assert seq.intrinsics == Intrinsics(585.0, 585.0, 320.0, 240.0, W, H)
    np.testing.assert_allclose(seq.timestamps, np.arange(N) / 30.0)
    frame = seq[4]
    assert frame.depth[1, 1] == 0.0 and frame.depth[0, 0] == 0.0  # 65535 and 0: no reading
    np.testing.assert_allclose(frame.depth[5:, 5:], make_depth(4)[5:, 5:], atol=1e-3)
    np.testing.assert_allclose(frame.gt_pose, make_pose(4), atol=1e-9)


def test_sevenscenes_intrinsics_file_then_sidecar_then_override(sevenscenes_root: Path) -> None:
    np.savetxt(
        sevenscenes_root / "camera-intrinsics.txt", [[40.0, 0, 16.0], [0, 41.0, 12.0], [0, 0, 1]]
    )
    assert open_sequence(sevenscenes_root).intrinsics == Intrinsics(40, 41, 16, 12, W, H)
    write_camera_yaml(sevenscenes_root, "fx: 50\ndepth_scale: 500\n")
    seq = open_sequence(sevenscenes_root)
    assert seq.intrinsics == Intrinsics(50, 41, 16, 12, W, H)
    assert seq.depth_scale == 500.0
    np.testing.assert_allclose(seq[0].depth[5:, 5:], 2 * make_depth(0)[5:, 5:], atol=3e-3)
    override = Intrinsics(1, 1, 1, 1, W, H)
    assert open_sequence(sevenscenes_root, intrinsics=override).intrinsics == override


def test_overrides_beat_sidecar_and_ignore_none(sevenscenes_root: Path) -> None:
    write_camera_yaml(sevenscenes_root, "fx: 50\nfps: 15\n")
    seq = open_sequence(sevenscenes_root, overrides={"fx": 60.0, "fy": None, "depth_scale": 2000.0})
    assert seq.intrinsics == Intrinsics(60, 585, 320, 240, W, H)
    assert seq.fps == 15.0 and seq.depth_scale == 2000.0
    np.testing.assert_allclose(seq[0].depth[5:, 5:], make_depth(0)[5:, 5:] / 2, atol=1e-3)
    with pytest.raises(DatasetError, match="camera overrides: unknown key 'depth_min'"):
        open_sequence(sevenscenes_root, overrides={"depth_min": 0.1})
    with pytest.raises(DatasetError, match="camera overrides: width must be a whole number"):
        open_sequence(sevenscenes_root, overrides={"width": 3.5})


def test_scannet_resizes_colour_and_marks_invalid_poses(scannet_root: Path) -> None:
    seq = open_sequence(scannet_root)
    assert seq.format == "scannet"
    assert seq.intrinsics == Intrinsics(28.0, 29.0, 15.0, 11.0, W, H)
    frame = seq[1]
    assert frame.rgb.shape == (H, W, 3)
    # JPEG is lossy: compare the constant red channel loosely.
    assert abs(float(frame.rgb[..., 0].mean()) - 200.0) < 4.0
    np.testing.assert_allclose(frame.depth[1:], make_depth(1)[1:], atol=1e-3)
    assert seq[2].gt_pose is None
    poses = seq.gt_poses()
    assert np.isnan(poses[2]).all() and np.allclose(poses[3], make_pose(3))


def test_scannet_without_intrinsic_file_needs_sidecar(scannet_root: Path) -> None:
    (scannet_root / "intrinsic" / "intrinsic_depth.txt").unlink()
    with pytest.raises(DatasetError, match="intrinsic_depth.txt"):
        open_sequence(scannet_root)
    write_camera_yaml(scannet_root)
    assert open_sequence(scannet_root).intrinsics.fx == 30.0


def test_tum_association_ground_truth_and_calibration(tum_root: Path) -> None:
    seq = open_sequence(tum_root)
    assert seq.format == "tum"
    assert list(seq.indices) == [0, 1, 2, 4, 5]  # row 3 has no depth within 0.02 s
    np.testing.assert_allclose(seq.timestamps, TUM_T0 + np.array([0, 1, 2, 4, 5]) / 30.0)
    assert (seq.intrinsics.fx, seq.intrinsics.cy) == (517.3, 255.3)  # freiburg1
    assert seq.fps == pytest.approx(30.0, rel=1e-3)
    assert seq.has_gt
    assert seq[1].gt_pose is not None and seq[3].gt_pose is None  # gt ends at ~0.11 s
    # Frame 2 (t = 0.0667 s) pairs with the gt line at 0.071 s (k = 7).
    np.testing.assert_allclose(seq[2].gt_pose[:3, 3], [0.07, 0, 0], atol=1e-12)
    np.testing.assert_allclose(seq[2].depth, make_depth(2), atol=1 / 5000)
    poses = seq.gt_poses()
    assert np.isfinite(poses[:3]).all() and np.isnan(poses[3:]).all()
    with pytest.raises(DatasetError, match="within 0.005 s"):  # depth lags 8 ms
        open_sequence(tum_root, max_dt=0.005)


def test_tum_without_freiburg_name_needs_sidecar(tum_root: Path) -> None:
    renamed = tum_root.rename(tum_root.parent / "my_capture")
    with pytest.raises(DatasetError, match="freiburg") as e:
        open_sequence(renamed)
    assert str(renamed) in str(e.value)
    write_camera_yaml(renamed)
    assert open_sequence(renamed).intrinsics.fx == 30.0


def test_tum_bad_lines_name_file_and_line(tum_root: Path) -> None:
    with open(tum_root / "depth.txt", "a") as f:
        f.write("not-a-time depth/x.png\n")
    with pytest.raises(DatasetError, match=r"depth\.txt:7: 'not-a-time' is not a number"):
        open_sequence(tum_root)


def test_tum_bad_ground_truth_line(tum_root: Path) -> None:
    with open(tum_root / "groundtruth.txt", "a") as f:
        f.write("1305031103.0 1 2 3\n")
    with pytest.raises(DatasetError, match=r"groundtruth\.txt:15: expected"):
        open_sequence(tum_root)


def test_associate_pairs_each_stamp_once_closest_first() -> None:
    rgb = np.array([0.0, 0.033, 0.066, 0.2])
    depth = np.array([0.017, 0.07, 0.5])
    # 0.017 is 0.017 from rgb 0 and 0.016 from rgb 1: rgb 1 takes it, rgb 0 gets nothing.
    assert associate(rgb, depth, 0.02) == [(1, 0), (2, 1)]
    assert associate(rgb, depth, 0.001) == []
    assert associate(rgb, np.array([0.07, 0.017]), 0.02) == [(1, 1), (2, 0)]


# -- detection, selection, laziness ---------------------------------------------------------


def test_detect_each_layout(
    replica_root: Path, sevenscenes_root: Path, scannet_root: Path, tum_root: Path
) -> None:
    assert detect_format(replica_root) == "replica"
    assert detect_format(sevenscenes_root) == "7scenes"
    assert detect_format(scannet_root) == "scannet"
    assert detect_format(tum_root) == "tum"


def test_forced_format_and_unknown_format(sevenscenes_root: Path) -> None:
    assert open_sequence(sevenscenes_root, fmt="7-Scenes").format == "7scenes"
    with pytest.raises(DatasetError, match="unknown dataset format 'kitti'"):
        open_sequence(sevenscenes_root, fmt="kitti")
    with pytest.raises(DatasetError, match="results"):
        open_sequence(sevenscenes_root, fmt="replica")


def test_unknown_layout_and_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="not a known RGB-D sequence layout") as e:
        open_sequence(tmp_path)
    assert str(tmp_path) in str(e.value)
    with pytest.raises(DatasetError, match="no such folder") as e:
        open_sequence(tmp_path / "absent")
    assert str(tmp_path / "absent") in str(e.value)


def test_frames_selection_keeps_indices_timestamps_and_poses(replica_root: Path) -> None:
    seq = open_sequence(replica_root, frames="1:5:2")
    assert list(seq.indices) == [1, 3]
    np.testing.assert_allclose(seq.timestamps, [0.1, 0.3])
    assert [f.index for f in seq] == [1, 3]
    assert seq[1].timestamp == pytest.approx(0.3)
    np.testing.assert_allclose(seq.gt_poses()[1], make_pose(3))
    assert list(open_sequence(replica_root, frames=slice(None, 2)).indices) == [0, 1]
    assert list(seq[::-1].indices) == [3, 1] and seq[-1].index == 3
    with pytest.raises(DatasetError, match="'7:' select none of the 5 frames"):
        open_sequence(replica_root, frames="7:")
    with pytest.raises(IndexError):
        seq[2]


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("0:300", slice(0, 300)),
        (":100", slice(None, 100)),
        ("50:", slice(50, None)),
        ("::2", slice(None, None, 2)),
        ("10:200:5", slice(10, 200, 5)),
        (" 1 : 4 ", slice(1, 4)),
    ],
)
def test_parse_frames_accepts(spec: str, expected: slice) -> None:
    assert parse_frames(spec) == expected


@pytest.mark.parametrize("spec", ["5", "-1:3", "a:b", "1:2:3:4", "::0", ""])
def test_parse_frames_rejects_naming_the_spec(spec: str) -> None:
    with pytest.raises(DatasetError, match="START:STOP") as e:
        parse_frames(spec)
    assert repr(spec) in str(e.value)


def test_opening_reads_no_images(replica_root: Path) -> None:
    bad = replica_root / "results" / "frame000003.png"
    bad.write_bytes(b"not an image")
    seq = open_sequence(replica_root)  # fine: images are read on access only
    assert seq[2].index == 2
    with pytest.raises(DatasetError, match="cannot read colour image") as e:
        seq[3]
    assert str(bad) in str(e.value)


# -- bad input ------------------------------------------------------------------------------


def test_missing_depth_names_first_missing_index(replica_root: Path) -> None:
    (replica_root / "results" / "depth000002.png").unlink()
    (replica_root / "results" / "depth000004.png").unlink()
    with pytest.raises(DatasetError, match="first missing index 2") as e:
        open_sequence(replica_root)
    assert str(replica_root / "results") in str(e.value)


def test_depth_must_be_uint16(sevenscenes_root: Path) -> None:
    path = sevenscenes_root / "frame-000001.depth.png"
    cv2.imwrite(str(path), np.full((H, W), 7, np.uint8))
    seq = open_sequence(sevenscenes_root)
    with pytest.raises(DatasetError, match="uint16 image, got uint8") as e:
        seq[1]
    assert str(path) in str(e.value)


def test_colour_depth_size_mismatch(replica_root: Path) -> None:
    path = replica_root / "results" / "frame000001.png"
    write_rgb(path, make_rgb(1, W + 2, H))
    with pytest.raises(DatasetError, match="colour is 34x24 but its depth") as e:
        open_sequence(replica_root)[1]
    assert str(path) in str(e.value)


def test_image_size_must_match_intrinsics(replica_root: Path) -> None:
    write_camera_yaml(replica_root, "fx: 30\nfy: 30\ncx: 15\ncy: 11\nwidth: 64\nheight: 48\n")
    with pytest.raises(DatasetError, match="image is 32x24 but the intrinsics say 64x48") as e:
        open_sequence(replica_root)[0]
    assert str(replica_root / "results" / "depth000000.png") in str(e.value)


def test_pose_file_must_hold_4x4_numbers(sevenscenes_root: Path) -> None:
    path = sevenscenes_root / "frame-000002.pose.txt"
    np.savetxt(path, make_pose(2)[:3])
    seq = open_sequence(sevenscenes_root)
    with pytest.raises(DatasetError, match="expected 4x4 = 16 numbers, found 12") as e:
        seq.gt_poses()
    assert str(path) in str(e.value)
    path.write_text("1 0 0 0\n0 1 0 0\n0 0 1 zero\n0 0 0 1\n")
    with pytest.raises(DatasetError, match="found text"):
        seq[2]


def test_pose_must_be_rigid(sevenscenes_root: Path) -> None:
    path = sevenscenes_root / "frame-000001.pose.txt"
    pose = make_pose(1)
    pose[:3, :3] *= 1.01
    np.savetxt(path, pose)
    with pytest.raises(DatasetError, match="not a rigid transform") as e:
        open_sequence(sevenscenes_root)[1]
    assert str(path) in str(e.value)
    pose[:3, :3] /= 1.01
    pose[:3, :3] *= 1.0002  # real ground truth is this far off: accepted
    np.savetxt(path, pose)
    assert open_sequence(sevenscenes_root)[1].gt_pose is not None


def test_traj_txt_errors_name_file_and_line(replica_root: Path) -> None:
    traj = replica_root / "traj.txt"
    lines = traj.read_text().splitlines()
    lines[3] = "1 0 0 0 0 1 0 0 0 0 1 0"
    traj.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"traj\.txt:4: expected 16 numbers .* found 12"):
        open_sequence(replica_root).gt_poses()
    traj.write_text("\n".join(lines[:3]) + "\n")
    with pytest.raises(DatasetError, match="has 3 poses, no line for frame 4"):
        open_sequence(replica_root)[4]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("fx: 30\nfocal: 2\n", "unknown key 'focal'"),
        ("fx: -3\n", "fx must be a finite positive number"),
        ("width: 31.5\n", "width must be a whole number"),
        ("fps: fast\n", "fps must be a number"),
        ("- 1\n- 2\n", "expected a mapping"),
        ("fx: [1\n", "cannot parse YAML"),
    ],
)
def test_sidecar_errors_name_file_and_key(replica_root: Path, text: str, message: str) -> None:
    write_camera_yaml(replica_root, text)
    with pytest.raises(DatasetError, match=message) as e:
        open_sequence(replica_root)
    assert str(replica_root / "camera.yaml") in str(e.value)


# -- the info command -----------------------------------------------------------------------


def _app() -> typer.Typer:
    app = typer.Typer()
    app.command()(info)

    @app.callback()
    def main() -> None:
        """Test app."""

    return app


def test_info_text_and_json(replica_root: Path) -> None:
    runner = CliRunner()
    result = runner.invoke(_app(), ["info", str(replica_root), "--frames", "1:"])
    assert result.exit_code == 0, result.output
    assert "replica" in result.output and "4 (indices 1..4" in result.output
    assert "32x24" in result.output and "ground truth yes" in result.output
    result = runner.invoke(_app(), ["info", str(replica_root), "--json", "--samples", "2"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["frames"] == N and summary["format"] == "replica"
    assert summary["depth"]["sampled_indices"] == [0, 4]
    assert summary["depth"]["min_m"] == pytest.approx(1.0, abs=1e-3)
    assert summary["depth"]["max_m"] == pytest.approx(2.4, abs=1e-3)
    assert summary["depth"]["valid_fraction"] == pytest.approx(1 - 1 / (W * H))
    lengths = [np.linalg.norm(make_pose(i + 1)[:3, 3] - make_pose(i)[:3, 3]) for i in range(4)]
    assert summary["ground_truth"]["trajectory_length_m"] == pytest.approx(sum(lengths))


def test_info_error_exits_2_with_message(tmp_path: Path) -> None:
    result = CliRunner().invoke(_app(), ["info", str(tmp_path / "nope")])
    assert result.exit_code == 2
    assert "no such folder" in result.output and "Traceback" not in result.output
    result = CliRunner().invoke(_app(), ["info", str(tmp_path), "--frames", "x"])
    assert result.exit_code == 2 and "START:STOP" in result.output


def test_info_camera_overrides_from_the_command_line(tmp_path) -> None:
    import typer
    from typer.testing import CliRunner

    from cpslam.common.datasets.cli import info
    from cpslam.tools.synth import generate

    out = generate(tmp_path / "s", frames=3, width=64, height=48)
    app = typer.Typer()
    app.command()(info)
    seq = str(out.agent_dirs[0])
    result = CliRunner().invoke(app, [seq, "--camera", "fx=100", "--camera", "cx=30", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["intrinsics"]["fx"] == 100 and data["intrinsics"]["cx"] == 30
    result = CliRunner().invoke(app, [seq, "--camera", "fx"])
    assert result.exit_code == 2 and "expected KEY=NUMBER" in result.output
    result = CliRunner().invoke(app, [seq, "--camera", "focal=3"])
    assert result.exit_code == 2 and "focal" in result.output


def test_dataset_gt_writes_the_frames_that_have_ground_truth(tum_root: Path,
                                                             tmp_path: Path) -> None:
    from cpslam.common.datasets.cli import gt
    from cpslam.common.trajectory import read_tum

    app = typer.Typer()
    app.command()(gt)
    seq = open_sequence(tum_root)
    poses = seq.gt_poses()
    known = np.isfinite(poses[:, 0, 0])
    assert 0 < known.sum() < len(seq)  # the fixture's ground truth ends early
    out = tmp_path / "gt.tum"
    result = CliRunner().invoke(app, [str(tum_root), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert f"{known.sum()}/{len(seq)} frames" in result.output
    stamps, written = read_tum(out)
    np.testing.assert_allclose(stamps, np.asarray(seq.timestamps)[known], atol=1e-6)
    np.testing.assert_allclose(written, poses[known], atol=1e-8)

    (tum_root / "groundtruth.txt").unlink()
    result = CliRunner().invoke(app, [str(tum_root), "--out", str(tmp_path / "none.tum")])
    assert result.exit_code == 2 and "no ground truth" in result.output
    assert not (tmp_path / "none.tum").exists()
