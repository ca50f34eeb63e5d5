import json

import numpy as np
import pytest

from cpslam.common.ply import write_ply
from cpslam.common.rundir import create_run_dir, peak_rss_mb, write_json


def test_ply_round_trip_with_open3d(tmp_path) -> None:
    import open3d as o3d

    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(100, 3)).astype(np.float32)
    colors = rng.integers(0, 256, size=(100, 3), dtype=np.uint8)
    path = write_ply(tmp_path / "p.ply", xyz, colors)
    cloud = o3d.io.read_point_cloud(str(path))
    np.testing.assert_allclose(np.asarray(cloud.points), xyz, atol=1e-6)
    np.testing.assert_allclose(np.asarray(cloud.colors) * 255, colors, atol=0.5)


def test_ply_rejects_bad_shapes(tmp_path) -> None:
    with pytest.raises(ValueError, match=r"xyz must be \[N, 3\]"):
        write_ply(tmp_path / "p.ply", np.zeros((3, 2)))
    with pytest.raises(ValueError, match="colors must be uint8"):
        write_ply(tmp_path / "p.ply", np.zeros((3, 3)), np.zeros((3, 3), dtype=float))


def test_run_dirs_are_unique_and_named(tmp_path) -> None:
    a = create_run_dir(tmp_path)
    b = create_run_dir(tmp_path)
    assert a != b and a.is_dir() and b.is_dir()
    assert create_run_dir(tmp_path, "demo") == tmp_path / "demo"


def test_write_json_converts_numpy(tmp_path) -> None:
    path = write_json(tmp_path / "m.json", {"a": np.float32(1.5), "b": np.arange(3)})
    assert json.loads(path.read_text()) == {"a": 1.5, "b": [0, 1, 2]}
    assert peak_rss_mb() > 10
