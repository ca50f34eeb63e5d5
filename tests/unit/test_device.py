import os

import pytest
import torch

from cpslam.common.device import (
    configure_torch,
    resolve_device,
    resolve_num_threads,
    usable_cores,
)


def test_cpu_and_auto() -> None:
    assert resolve_device("cpu") == "cpu"
    expected = "cuda:0" if torch.cuda.is_available() else "cpu"
    assert resolve_device("auto") == expected


@pytest.mark.parametrize("bad", ["gpu", "cuda:x", "", "CPU"])
def test_bad_spec_names_the_value(bad: str) -> None:
    with pytest.raises(ValueError, match="expected auto, cpu, cuda or cuda:N"):
        resolve_device(bad)


@pytest.mark.skipif(torch.cuda.is_available(), reason="machine has CUDA")
def test_cuda_without_gpu_is_an_error() -> None:
    with pytest.raises(ValueError, match="CUDA is not available"):
        resolve_device("cuda")


def test_auto_threads_divide_the_usable_cores() -> None:
    assert resolve_num_threads("auto", share=1, cores=8) == 8
    assert resolve_num_threads("auto", share=3, cores=8) == 2
    assert resolve_num_threads("auto", share=3, cores=2) == 1  # never below one thread
    assert resolve_num_threads(3, share=4, cores=2) == 3  # a number is taken as it is
    assert resolve_num_threads(None) is None  # torch's own default
    with pytest.raises(ValueError, match="share"):
        resolve_num_threads("auto", share=0, cores=2)
    with pytest.raises(ValueError, match="run.num_threads 'many'"):
        resolve_num_threads("many")


def test_usable_cores_honours_a_cgroup_quota(tmp_path) -> None:
    affinity = len(os.sched_getaffinity(0))
    cpu_max = tmp_path / "cpu.max"
    cpu_max.write_text("max 100000\n")
    assert usable_cores(cpu_max) == affinity
    cpu_max.write_text("100000 100000\n")  # docker run --cpus 1
    assert usable_cores(cpu_max) == 1
    cpu_max.write_text("50000 100000\n")  # half a core still gets one thread
    assert usable_cores(cpu_max) == 1
    assert usable_cores(tmp_path / "missing") == affinity


def test_configure_torch_sets_threads_and_determinism() -> None:
    before = torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()
    try:
        assert configure_torch(1, True) == 1 == torch.get_num_threads()
        assert torch.are_deterministic_algorithms_enabled()
        assert os.environ["CUBLAS_WORKSPACE_CONFIG"] in (":4096:8", ":16:8")
        assert configure_torch(None, False) == 1  # threads left as they were
        assert not torch.are_deterministic_algorithms_enabled()
    finally:
        torch.set_num_threads(before[0])
        torch.use_deterministic_algorithms(before[1], warn_only=True)
