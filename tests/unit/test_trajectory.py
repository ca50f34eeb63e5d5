"""TUM trajectory io: round trips, evo compatibility, and error messages naming path and line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cpslam.common.geometry import se3_exp
from cpslam.common.trajectory import (
    TUM_HEADER,
    Trajectory,
    TrajectoryFormatError,
    read_tum,
    write_tum,
)


def random_trajectory(n: int = 40, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    xi = rng.normal(size=(n, 6))
    xi[:, 3:] *= 0.8
    stamps = 1305031102.175304 + np.cumsum(rng.uniform(0.01, 0.05, size=n))
    return stamps, se3_exp(xi)


def test_write_read_round_trip(tmp_path: Path) -> None:
    stamps, poses = random_trajectory()
    path = tmp_path / "sub" / "dir" / "traj.tum"
    write_tum(path, stamps, poses)
    lines = path.read_text().splitlines()
    assert lines[0] == TUM_HEADER and len(lines) == 41
    assert len(lines[1].split()) == 8
    stamps_back, poses_back = read_tum(path)
    assert stamps_back.dtype == np.float64 and poses_back.shape == (40, 4, 4)
    np.testing.assert_allclose(stamps_back, stamps, rtol=0, atol=1e-6)
    np.testing.assert_allclose(poses_back, poses, atol=5e-9)
    # the quaternion is written with w >= 0
    assert all(float(line.split()[7]) >= 0.0 for line in lines[1:])


def test_readable_by_evo(tmp_path: Path) -> None:
    file_interface = pytest.importorskip("evo.tools.file_interface")
    stamps, poses = random_trajectory(10)
    write_tum(tmp_path / "t.tum", stamps, poses)
    traj = file_interface.read_tum_trajectory_file(str(tmp_path / "t.tum"))
    np.testing.assert_allclose(traj.timestamps, stamps, atol=1e-6)
    np.testing.assert_allclose(np.stack(traj.poses_se3), poses, atol=5e-9)


def test_reader_skips_comments_and_accepts_commas(tmp_path: Path) -> None:
    path = tmp_path / "gt.txt"
    path.write_text(
        "# ground truth trajectory\n# file: 'rgbd_dataset'\n\n"
        "1.0 0 0 0 0 0 0 1\n"
        "   \n"
        "2.5,1,2,3,0,0,0.7071067811865476,0.7071067811865476\n"
    )
    stamps, poses = read_tum(path)
    np.testing.assert_array_equal(stamps, [1.0, 2.5])
    np.testing.assert_array_equal(poses[0], np.eye(4))
    np.testing.assert_allclose(poses[1, :3, 3], [1, 2, 3])
    np.testing.assert_allclose(poses[1, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)


@pytest.mark.parametrize(
    "bad_line, message",
    [
        ("3.0 0 0 0 0 0 1", "expected 8 fields"),
        ("3.0 0 0 zero 0 0 0 1", "must be numbers"),
        ("3.0 0 0 nan 0 0 0 1", "finite"),
        ("3.0 0 0 0 0 0 0 0", "zero-norm quaternion"),
        ("3.0 0 0 0 0 0 0 2", "not 1"),
        ("2.0 0 0 0 0 0 0 1", "not after the previous"),
    ],
)
def test_reader_errors_name_path_and_line(tmp_path: Path, bad_line: str, message: str) -> None:
    path = tmp_path / "bad.tum"
    path.write_text(f"{TUM_HEADER}\n1.0 0 0 0 0 0 0 1\n\n2.0 0 0 0 0 0 0 1\n{bad_line}\n")
    with pytest.raises(TrajectoryFormatError, match=message) as info:
        read_tum(path)
    assert f"{path}:5:" in str(info.value)
    assert isinstance(info.value, ValueError)


def test_reader_rejects_missing_and_empty(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nope.tum"):
        read_tum(tmp_path / "nope.tum")
    empty = tmp_path / "empty.tum"
    empty.write_text(f"{TUM_HEADER}\n\n")
    with pytest.raises(TrajectoryFormatError, match="no poses") as info:
        read_tum(empty)
    assert str(empty) in str(info.value)


def test_writer_rejects_bad_input(tmp_path: Path) -> None:
    stamps, poses = random_trajectory(5)
    out = tmp_path / "out.tum"
    with pytest.raises(ValueError, match=r"\(5, 4, 4\)"):
        write_tum(out, stamps, poses[:4])
    with pytest.raises(ValueError, match="strictly increasing"):
        write_tum(out, stamps[::-1], poses)
    bent = poses.copy()
    bent[3, :3, :3] *= 1.1
    with pytest.raises(ValueError, match=r"index \[3\].*not rigid"):
        write_tum(out, stamps, bent)
    with pytest.raises(ValueError, match="no poses"):
        write_tum(out, np.zeros(0), np.zeros((0, 4, 4)))
    assert not out.exists()


def test_trajectory_dataclass(tmp_path: Path) -> None:
    stamps, poses = random_trajectory(6)
    traj = Trajectory(stamps, poses)
    assert len(traj) == 6
    np.testing.assert_array_equal(traj.positions, poses[:, :3, 3])
    traj.write(tmp_path / "t.tum")
    back = Trajectory.read(tmp_path / "t.tum")
    np.testing.assert_allclose(back.poses, poses, atol=5e-9)
    with pytest.raises(ValueError, match="stamps"):
        Trajectory(np.zeros((2, 2)), poses[:2])
