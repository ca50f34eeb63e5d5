"""Bags as datasets: ROS 1, ROS 2 (sqlite3) and MCAP files written with `rosbags` from the first
ten 7-Scenes frames read back exactly; topic detection, pairing tolerance and error cases.
"""

from __future__ import annotations

import json
import pickle
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import typer
from bag_writer import LATENCY_NS, stamp_ns, write_bag
from typer.testing import CliRunner

from cpslam.common.camera import Intrinsics
from cpslam.common.datasets import DatasetError, RGBDSequence, open_sequence
from cpslam.common.datasets.cli import info

pytest.importorskip("rosbags", reason="needs the bags extra: pip install 'cpslam[bags]'")
pytestmark = pytest.mark.data

COLOUR = "/camera/color/image_raw"
POSE = "/ground_truth/pose"


@pytest.fixture(scope="module")
def source(kitchen_path: Path) -> RGBDSequence:
    return open_sequence(kitchen_path, frames="0:10")


@pytest.fixture(scope="module")
def bags(source: RGBDSequence, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A ROS 1 bag (raw, 16UC1), a ROS 2 sqlite3 bag (PNG colour, compressedDepth) and an MCAP
    file on its own (raw, 32FC1)."""
    out = tmp_path_factory.mktemp("bags")
    ros2_mcap = write_bag(out / "mcap_bag", source, "mcap", depth_encoding="32FC1")
    mcap = out / "kitchen.mcap"
    shutil.move(next(ros2_mcap.glob("*.mcap")), mcap)  # the storage file without metadata.yaml
    return {
        "ros1": write_bag(out / "kitchen.bag", source, "ros1"),
        "ros2": write_bag(out / "kitchen_ros2", source, "ros2", compressed=True),
        "mcap": mcap,
    }


@pytest.mark.parametrize("kind", ["ros1", "ros2", "mcap"])
def test_bag_reads_back_exactly(kind: str, bags: dict[str, Path], source: RGBDSequence) -> None:
    seq = open_sequence(bags[kind])
    assert seq.format == "bag" and len(seq) == len(source)
    assert seq.intrinsics == source.intrinsics
    assert list(seq.indices) == list(range(10))
    # header stamps in whole nanoseconds, converted once to float seconds
    expected = np.array([np.float64(stamp_ns(t)) * 1e-9 for t in source.timestamps])
    assert np.array_equal(seq.timestamps, expected)
    assert seq.fps == pytest.approx(30.0, rel=1e-6)
    assert seq.has_gt
    for a, b in zip(source, seq, strict=True):
        assert b.timestamp == np.float64(stamp_ns(a.timestamp)) * 1e-9
        assert b.rgb.dtype == np.uint8 and np.array_equal(a.rgb, b.rgb)
        assert b.depth.dtype == np.float32 and np.array_equal(a.depth, b.depth)
        # written as translation + quaternion: equal up to float64 rounding
        np.testing.assert_allclose(b.gt_pose, a.gt_pose, rtol=0, atol=1e-12)
    np.testing.assert_allclose(seq.gt_poses(), source.gt_poses(), rtol=0, atol=1e-12)


def test_bag_frames_selection_and_topics(bags: dict[str, Path], source: RGBDSequence) -> None:
    seq = open_sequence(bags["ros2"], frames="2:9:3")
    assert list(seq.indices) == [2, 5, 8]
    assert seq.topics["rgb"] == COLOUR + "/compressed"
    assert seq.topics["depth"] == "/camera/depth/image_raw/compressedDepth"
    assert seq.topics["info"] == "/camera/color/camera_info" and seq.topics["pose"] == POSE
    assert np.array_equal(seq[1].rgb, source[5].rgb)
    assert np.array_equal(seq[2].depth, source[8].depth)
    assert seq[0:2][1].index == 5  # a selection of a selection still finds its messages
    copy = pickle.loads(pickle.dumps(seq))  # e.g. for another process: opens its own reader
    assert copy.access is not seq.access and np.array_equal(copy[2].rgb, source[8].rgb)


def test_dataset_info_on_a_bag(bags: dict[str, Path]) -> None:
    app = typer.Typer()
    app.command()(info)
    result = CliRunner().invoke(app, [str(bags["ros1"]), "--frames", "0:6", "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["format"] == "bag" and summary["frames"] == 6
    assert summary["intrinsics"] == {"fx": 585.0, "fy": 585.0, "cx": 320.0, "cy": 240.0}
    assert summary["depth_scale"] == 1000.0
    assert summary["ground_truth"]["frames"] == 6
    assert summary["topics"] == {"rgb": COLOUR, "depth": "/camera/depth/image_raw",
                                 "info": "/camera/color/camera_info", "pose": POSE}
    result = CliRunner().invoke(app, [str(bags["ros1"]), "--topic-pose", "none"])
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert "ground truth no" in text
    assert ("topics rgb /camera/color/image_raw, depth /camera/depth/image_raw, "
            "info /camera/color/camera_info") in text


def test_depth_pairing_tolerance(source: RGBDSequence, tmp_path: Path) -> None:
    """Colour pairs with the depth nearest in header time, within max_dt (default 20 ms)."""
    near = write_bag(tmp_path / "near.bag", source[:4], "ros1", depth_offset_ns=15_000_000)
    seq = open_sequence(near)
    assert len(seq) == 4 and np.array_equal(seq[3].depth, source[3].depth)
    assert seq.timestamps[0] == np.float64(stamp_ns(source.timestamps[0])) * 1e-9  # colour's
    with pytest.raises(DatasetError, match=r"near\.bag: no colour image on .* within 0\.01 s"):
        open_sequence(near, max_dt=0.01)
    # 30 ms late, depth i is nearest to colour i+1 (3.3 ms away): the first colour image has
    # no partner and is skipped, the others keep their own index and stamp
    late = open_sequence(write_bag(tmp_path / "late.bag", source[:4], "ros1",
                                   depth_offset_ns=30_000_000))
    assert list(late.indices) == [1, 2, 3]
    assert np.array_equal(late[0].rgb, source[1].rgb)
    assert np.array_equal(late[0].depth, source[0].depth)
    far = write_bag(tmp_path / "far.bag", source[:4], "ros1", depth_offset_ns=500_000_000)
    with pytest.raises(DatasetError, match=r"far\.bag: no colour image on .* within 0\.02 s"):
        open_sequence(far)


def test_header_stamps_not_receive_times(bags: dict[str, Path], source: RGBDSequence) -> None:
    seq = open_sequence(bags["ros1"])
    receive = np.float64(stamp_ns(source.timestamps[0]) + LATENCY_NS) * 1e-9
    assert seq.timestamps[0] != receive


def test_missing_and_wrong_topics(bags: dict[str, Path]) -> None:
    bag = bags["ros1"]
    with pytest.raises(DatasetError, match=r"kitchen\.bag: --topic-rgb /nope: no such topic.*"
                       r"/camera/color/image_raw \(sensor_msgs/msg/Image\)"):
        open_sequence(bag, topics={"rgb": "/nope"})
    with pytest.raises(DatasetError, match=r"--topic-info /ground_truth/pose is "
                       r"geometry_msgs/msg/PoseStamped; expected sensor_msgs/msg/CameraInfo"):
        open_sequence(bag, topics={"info": POSE})
    with pytest.raises(DatasetError, match=r"kitchen\.bag: topic /camera/color/image_raw: "
                       r"depth encoding 'rgb8' is not supported; expected one of 16UC1"):
        open_sequence(bag, topics={"rgb": "/camera/depth/image_raw", "depth": COLOUR})
    # the only colour topic named as depth leaves no colour candidate
    with pytest.raises(DatasetError, match=r"kitchen\.bag: no colour image topic found .*the "
                       r"bag has: .*Name it with --topic-rgb"):
        open_sequence(bag, topics={"depth": COLOUR})


def test_ambiguous_topics(source: RGBDSequence, tmp_path: Path) -> None:
    two = write_bag(tmp_path / "two.bag", source[:2], "ros1",
                    extra=(("/camera2/color/image_raw", "colour"), ("/mocap/pose", "pose")))
    with pytest.raises(DatasetError, match=r"two\.bag: 2 candidate colour image topics: "
                       r"/camera/color/image_raw, /camera2/color/image_raw; choose one with "
                       r"--topic-rgb TOPIC"):
        open_sequence(two)
    with pytest.raises(DatasetError, match=r"2 candidate pose topics: .*--topic-pose none"):
        open_sequence(two, topics={"rgb": COLOUR})
    seq = open_sequence(two, topics={"rgb": "/camera2/color/image_raw", "pose": "/mocap/pose"})
    assert seq.topics["rgb"] == "/camera2/color/image_raw" and seq.has_gt
    assert not open_sequence(two, topics={"rgb": COLOUR, "pose": "none"}).has_gt


def test_ground_truth_from_tf(source: RGBDSequence, tmp_path: Path) -> None:
    """/tf is read only when named; a pair of frames picks the camera's transform."""
    bag = write_bag(tmp_path / "tf.bag", source[:3], "ros1", with_tf=True)
    assert open_sequence(bag).topics["pose"] == POSE  # not /tf
    with pytest.raises(DatasetError, match=r"tf\.bag: topic /tf has several frame pairs "
                       r"\(seen: camera:camera_optical, world:camera\); choose one with "
                       r"--topic-pose /tf:PARENT:CHILD"):
        open_sequence(bag, topics={"pose": "/tf"})
    with pytest.raises(DatasetError, match=r"topic /tf has no transform world -> nope"):
        open_sequence(bag, topics={"pose": "/tf:world:nope"})
    with pytest.raises(DatasetError, match=r"--topic-pose /ground_truth/pose:a:b: "
                       r"PARENT:CHILD frames apply to tf topics"):
        open_sequence(bag, topics={"pose": POSE + ":a:b"})
    seq = open_sequence(bag, topics={"pose": "/tf:/world:camera"})
    np.testing.assert_allclose(seq.gt_poses(), source[:3].gt_poses(), rtol=0, atol=1e-12)


def test_detection_in_a_realsense_like_bag(source: RGBDSequence, tmp_path: Path) -> None:
    """Raw and aligned depth are ambiguous; the colour topic's compressed twin and an infrared
    stream are not candidates; the camera info beside the chosen depth topic is taken."""
    aligned = "/camera/aligned_depth_to_color"
    bag = write_bag(tmp_path / "d435.bag", source[:2], "ros1", extra=(
        (COLOUR + "/compressed", "colour_compressed"), ("/camera/infra1/image_rect_raw", "mono"),
        (f"{aligned}/image_raw", "depth"), (f"{aligned}/camera_info", "info"),
        ("/camera/depth/camera_info", "info")))
    with pytest.raises(DatasetError, match=r"d435\.bag: 2 candidate depth image topics: "
                       rf"{aligned}/image_raw, /camera/depth/image_raw; choose one with "
                       r"--topic-depth TOPIC"):
        open_sequence(bag)
    seq = open_sequence(bag, topics={"depth": f"{aligned}/image_raw"})
    assert seq.topics == {"rgb": COLOUR, "depth": f"{aligned}/image_raw",
                          "info": f"{aligned}/camera_info", "pose": POSE}
    seq = open_sequence(bag, topics={"depth": "/camera/depth/image_raw"})
    assert seq.topics["info"] == "/camera/depth/camera_info"
    mono = open_sequence(bag, topics={"depth": f"{aligned}/image_raw",
                                      "rgb": "/camera/infra1/image_rect_raw"})
    assert np.array_equal(mono[0].rgb[:, :, 0], source[0].rgb[:, :, 1])


def test_no_camera_info_needs_intrinsics(source: RGBDSequence, tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "noinfo.bag", source[:2], "ros1", with_info=False,
                    with_pose=False)
    with pytest.raises(DatasetError, match=r"noinfo\.bag: no fx, fy, cx, cy for this bag "
                       r"sequence \(the bag has no sensor_msgs/CameraInfo topic"):
        open_sequence(bag)
    seq = open_sequence(bag, overrides={"fx": 585.0, "fy": 585.0, "cx": 320.0, "cy": 240.0})
    assert seq.intrinsics == Intrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)
    assert not seq.has_gt
    # the config's depth scale applies to 16UC1
    scaled = open_sequence(bag, intrinsics=seq.intrinsics, overrides={"depth_scale": 500.0})
    np.testing.assert_array_equal(scaled[0].depth, np.float32(2) * seq[0].depth)


def test_sizes_must_agree(bags: dict[str, Path]) -> None:
    with pytest.raises(DatasetError, match=r"kitchen\.bag: the intrinsics \(camera info "
                       r"/camera/color/camera_info, overrides or camera\.yaml\) are for 320x240 "
                       r"images but depth /camera/depth/image_raw is 640x480"):
        open_sequence(bags["ros1"], overrides={"width": 320, "height": 240})


def test_colour_and_depth_sizes_must_agree(source: RGBDSequence, tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "half.bag", source[:2], "ros1", depth_stride=2)
    with pytest.raises(DatasetError, match=r"half\.bag: colour /camera/color/image_raw is "
                       r"640x480 but depth /camera/depth/image_raw is 320x240; they must match"):
        open_sequence(bag)


def test_topics_are_for_bags_only(kitchen_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"topics \(rgb\) apply to bags only, this is a "
                       r"7scenes sequence"):
        open_sequence(kitchen_path, topics={"rgb": COLOUR})


def test_without_rosbags_says_how_to_install(bags: dict[str, Path],
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    with pytest.raises(DatasetError, match=r"kitchen\.bag: reading ROS bags and MCAP files "
                       r"needs the rosbags package; install it with pip install 'cpslam\[bags\]'"):
        open_sequence(bags["ros1"])


def test_not_a_bag(tmp_path: Path) -> None:
    broken = tmp_path / "broken.bag"
    broken.write_bytes(b"not a bag at all")
    with pytest.raises(DatasetError, match=r"broken\.bag: cannot read as a ROS bag"):
        open_sequence(broken)
    other = tmp_path / "notes.txt"
    other.write_text("x")
    with pytest.raises(DatasetError, match=r"notes\.txt: not a folder \(expected a sequence "
                       r"folder, or a bag"):
        open_sequence(other)
