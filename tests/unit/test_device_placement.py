"""The CUDA path without a GPU: no CPU-only assumption in the code that runs on the device.

Three checks a CPU build can make:
- a scan of the sources for patterns that break on CUDA (`.numpy()` on a tensor not first
  brought to the CPU; a seeded draw that does not say on which device it happens, which
  fails as soon as its generator lives on the GPU);
- `meta` tensors as a stand-in for a second device: torch refuses to mix them with CPU
  tensors exactly as it refuses CUDA ones, so a function given meta inputs must either
  finish with meta outputs or stop at the first step that needs the values (which meta
  tensors do not have), never at a device mismatch;
- the odometry imports nothing of zenoh, gtsam or open3d (the GPU machine has none of them).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

from cpslam.agent.aggregation import kmeans
from cpslam.common.camera import Intrinsics
from cpslam.common.field.decoders import FeatureCNN
from cpslam.common.field.points import NeuralPointMap
from cpslam.common.field.renderer import camera_rays
from cpslam.common.field.sampler import RaySampler

ROOT = Path(__file__).resolve().parents[2]
DEVICE_CODE = ("agent", "common", "server")
SEEDED_DRAWS = {"rand", "randn", "randint", "randperm", "rand_like", "randint_like"}
META = torch.device("meta")
MISMATCH = ("is not on the expected device", "Expected all tensors to be on the same device",
            "device type for generator", "must be on the same device")
NO_DATA = ("meta tensors", "meta tensor", "on the meta device")


def _sources() -> list[Path]:
    return sorted(p for d in DEVICE_CODE for p in (ROOT / d).rglob("*.py"))


def _calls(path: Path):
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            yield node


def cpu_only_patterns(path: Path) -> list[str]:
    """`file:line: what` for each CUDA-breaking pattern in one source file."""
    found = []
    rel = path.relative_to(ROOT)
    for call in _calls(path):
        attr = call.func.attr
        receiver = call.func.value
        if attr == "numpy" and not call.args:
            through_cpu = (isinstance(receiver, ast.Call) and isinstance(receiver.func,
                                                                         ast.Attribute)
                           and receiver.func.attr == "cpu")
            if not through_cpu:
                found.append(f"{rel}:{call.lineno}: .numpy() without .cpu(): "
                             f"{ast.unparse(call)[:80]}")
        elif (attr in SEEDED_DRAWS and isinstance(receiver, ast.Name) and receiver.id == "torch"
              and any(k.arg == "generator" for k in call.keywords)
              and not any(k.arg == "device" for k in call.keywords)):
            found.append(f"{rel}:{call.lineno}: seeded torch.{attr} without device=: "
                         f"{ast.unparse(call)[:80]}")
    return found


def test_device_code_has_no_cpu_only_patterns() -> None:
    found = [hit for path in _sources() for hit in cpu_only_patterns(path)]
    assert not found, "CPU-only patterns (they fail on CUDA):\n" + "\n".join(found)


def test_the_scan_finds_each_pattern(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    bad = tmp_path / "bad.py"
    bad.write_text("import torch\n"
                   "a = t.numpy()\n"
                   "b = t.detach().numpy()\n"
                   "c = t.cpu().numpy()\n"
                   "d = torch.randint(0, 5, (3,), generator=g)\n"
                   "e = torch.randint(0, 5, (3,), generator=g, device=g.device)\n"
                   "f = torch.rand(3)\n")
    hits = cpu_only_patterns(bad)
    assert [h.split(":")[1] for h in hits] == ["2", "3", "5"]


def reaches_data_or_finishes(fn: Callable[[], object]) -> object:
    """Run fn on meta inputs: its result, or None when it stopped where values are needed;
    fails on a device mismatch (a CPU tensor where the input's device was due)."""
    try:
        return fn()
    except (RuntimeError, NotImplementedError, ValueError) as error:
        text = str(error)
        if any(m in text for m in MISMATCH):
            pytest.fail(f"device mismatch (CPU-only assumption): {text}")
        if not any(m in text for m in NO_DATA):
            raise
        return None


def test_the_meta_probe_tells_a_mismatch_from_missing_values() -> None:
    eye = torch.eye(3, device=META)
    with pytest.raises(pytest.fail.Exception, match="device mismatch"):
        reaches_data_or_finishes(lambda: eye - torch.eye(3))
    assert reaches_data_or_finishes(lambda: bool(eye.any())) is None
    assert reaches_data_or_finishes(lambda: eye + 1).device == META


def test_point_map_keyframe_poses_check_on_their_device() -> None:
    point_map = NeuralPointMap(8, 0.1, 0, META)
    T = torch.eye(4, dtype=torch.float64, device=META)
    reaches_data_or_finishes(lambda: point_map.set_keyframe_poses(3, T))
    other = NeuralPointMap(8, 0.1, 1, META)
    reaches_data_or_finishes(lambda: point_map.merge(other, T))


def test_camera_rays_follow_the_pose_device() -> None:
    intr = Intrinsics(100.0, 100.0, 31.5, 23.5, 64, 48)
    u, v = torch.arange(5), torch.arange(5)  # pixel indices often come from the CPU
    o, d = camera_rays(intr, torch.eye(4, dtype=torch.float64, device=META), u, v)
    assert o.device == d.device == META and d.shape == (5, 3)


def test_feature_cnn_at_pixels_on_its_device() -> None:
    cnn = FeatureCNN(8).to(META)
    rgb = np.zeros((12, 16, 3), np.uint8)
    out = cnn.at_pixels(rgb, torch.tensor([1, 2, 3]), torch.tensor([4, 5, 6]))
    assert out.device == META and out.shape == (3, 8)


def test_ray_sampler_draws_on_the_cpu_generator_and_returns_on_the_depth_device() -> None:
    sampler = RaySampler(4, 2, near_lo=0.95, near_hi=1.05, far_hi=1.05, min_depth=0.001)
    gen = torch.Generator().manual_seed(0)
    t = sampler(torch.ones(7, device=META), gen, depth_range=(0.5, 2.0))
    assert t.device == META and t.shape == (7, 6)


def test_kmeans_seeding_on_another_device() -> None:
    reaches_data_or_finishes(lambda: kmeans(torch.zeros(20, 3, device=META), 4, seed=0))


def test_odometry_imports_no_network_graph_or_open3d() -> None:
    """The GPU machine has none of these: the odometry and the field must import without."""
    code = ("import sys, cpslam.agent.odometry, cpslam.common.field, cpslam.common.config; "
            "print(sorted(m for m in ('zenoh', 'gtsam', 'open3d') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300, cwd=ROOT / "tests")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "[]"


def test_recovery_relocalisation_without_open3d(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without open3d the keyframe registration offers no guess (it used to raise)."""
    from cpslam.agent import recovery

    monkeypatch.setitem(sys.modules, "open3d", None)  # import open3d now raises ImportError

    class NoKeyframes:
        def ids(self):  # reached only when the registration would run
            raise AssertionError("registration attempted without open3d")

    assert recovery._keyframe_guesses(object(), NoKeyframes(), object()) == {}
    assert recovery.rgbd_odometry(object(), object(), object()) is None
