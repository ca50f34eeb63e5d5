import os
import platform

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


_HEAP_PROBE = """
import ctypes, sys
from cpslam.common.device import retain_freed_memory
changed = retain_freed_memory() if sys.argv[1] == "retain" else False
libc = ctypes.CDLL(None)
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, (ctypes.c_size_t,)
libc.free.argtypes = (ctypes.c_void_p,)

class Info(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
        "fordblks", "keepcost")]

libc.mallinfo2.restype = Info
before = libc.mallinfo2().fordblks
libc.free(libc.malloc(8 << 20))
print(int(changed), libc.mallinfo2().fordblks - before)
"""


def _heap_probe(mode: str, env: dict[str, str] | None = None) -> tuple[bool, int]:
    """Whether a fresh process changed its allocator, and how many bytes more its heap holds
    free after an 8 MiB block was allocated and freed."""
    import subprocess
    import sys

    run_env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    run_env.update(env or {})
    out = subprocess.run([sys.executable, "-c", _HEAP_PROBE, mode], env=run_env, check=True,
                         capture_output=True, text=True).stdout.split()
    return out[0] == "1", int(out[1])


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's allocator only")
def test_freed_blocks_stay_in_the_heap() -> None:
    """An 8 MiB block is handed back to the OS by default and kept for the next allocation
    once the allocator is tuned; a threshold set in the environment is left alone."""
    import ctypes

    if not hasattr(ctypes.CDLL(None), "mallinfo2"):
        pytest.skip("glibc older than 2.33 has no mallinfo2")
    changed, kept = _heap_probe("default")
    assert not changed and kept < 1 << 20
    changed, kept = _heap_probe("retain")
    assert changed and kept >= 8 << 20
    assert _heap_probe("retain", {"MALLOC_TRIM_THRESHOLD_": "131072"})[0] is False
