"""Choose the torch device and the CPU thread count once, at the command line, and pass them
down."""

from __future__ import annotations

import ctypes
import os
import platform
import re
from pathlib import Path

_DEVICE_RE = re.compile(r"^(auto|cpu|cuda(:\d+)?)$")


def resolve_device(spec: str = "auto") -> str:
    """Turn `auto|cpu|cuda|cuda:N` into a concrete torch device string.

    `auto` picks the first CUDA device when one is usable and the CPU otherwise; asking for
    CUDA where there is none is an error rather than a silent fallback, so a user who asked
    for the GPU knows they are not getting it.
    """
    if not _DEVICE_RE.match(spec):
        raise ValueError(f"device {spec!r}: expected auto, cpu, cuda or cuda:N")
    import torch

    if spec == "auto":
        return "cuda:0" if torch.cuda.is_available() else "cpu"
    if spec.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ValueError(f"device {spec!r}: CUDA is not available on this machine")
        index = int(spec.split(":")[1]) if ":" in spec else 0
        if index >= torch.cuda.device_count():
            raise ValueError(
                f"device {spec!r}: only {torch.cuda.device_count()} CUDA device(s) present"
            )
        return f"cuda:{index}"
    return "cpu"


def usable_cores(cgroup_cpu_max: Path = Path("/sys/fs/cgroup/cpu.max")) -> int:
    """CPU cores this process may run on: its affinity mask, capped by a cgroup v2 CPU quota
    (`docker run --cpus`, Compose `cpus:`), which `os.cpu_count()` and torch both ignore."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        cores = os.cpu_count() or 1
    try:
        quota, period = cgroup_cpu_max.read_text().split()[:2]
        if quota != "max":
            cores = min(cores, int(quota) // int(period))
    except (OSError, ValueError):
        pass  # no cgroup v2 quota readable: the affinity mask stands
    return max(1, cores)


def resolve_num_threads(setting: int | str | None, share: int = 1,
                        cores: int | None = None) -> int | None:
    """Turn `run.num_threads` into a thread count for this process.

    A number is used as it is; `auto` divides the usable cores among `share` processes that a
    launcher starts on this machine side by side (at least one thread each); None leaves
    torch's own default (None returned).
    """
    if setting is None:
        return None
    if setting == "auto":
        if share < 1:
            raise ValueError(f"resolve_num_threads: share must be >= 1, got {share}")
        return max(1, (cores or usable_cores()) // share)
    if isinstance(setting, int) and not isinstance(setting, bool) and setting > 0:
        return setting
    raise ValueError(f"run.num_threads {setting!r}: expected a positive integer, auto or null")


def configure_torch(num_threads: int | str | None, deterministic: bool, share: int = 1) -> int:
    """Apply `run.num_threads` (see `resolve_num_threads`) and `run.deterministic`; return the
    thread count torch now uses.

    It also keeps freed memory in the process's heap (`retain_freed_memory`).

    Deterministic algorithms are what make a CPU run with more than one thread repeat itself:
    without them two 2-thread runs of the same 12 frames ended 3 cm apart, with them they are
    bit-identical, at the same speed, and one thread gives the same bits either way. On CUDA,
    ops with no deterministic kernel warn instead of failing (`warn_only`).
    """
    import torch

    retain_freed_memory()
    threads = resolve_num_threads(num_threads, share)
    if threads is not None:
        torch.set_num_threads(threads)
    if deterministic:
        # cuBLAS needs a fixed workspace for repeatable GEMMs; read when its handle is made.
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.use_deterministic_algorithms(deterministic, warn_only=True)
    return torch.get_num_threads()


# glibc's mallopt parameters (malloc.h) and the largest mmap threshold it accepts on 64 bits.
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_MMAP_THRESHOLD_MAX = 32 * 1024 * 1024
_TRIM_THRESHOLD = 1024 * 1024 * 1024


def retain_freed_memory() -> bool:
    """Keep memory that tensors free in the heap for the next ones, instead of giving it back
    to the OS; return whether the allocator was changed.

    Every render and backward pass allocates and frees per-pair tensors of a few MB. glibc
    hands such blocks back (munmap, or a trim of the heap's top) and the next allocation
    faults its pages in again, which costs system time on every frame (Open3D pays the
    same; docs/performance.md). With both thresholds set, blocks up to 32 MiB come from the
    heap and stay there; the resident memory stays at its peak. Nothing changes where the C
    library is not glibc or the environment sets either threshold (MALLOC_TRIM_THRESHOLD_,
    MALLOC_MMAP_THRESHOLD_ or their GLIBC_TUNABLES), which is then the user's choice.
    """
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    if any(f"MALLOC_{name.upper()}_" in os.environ or f"glibc.malloc.{name}" in tunables
           for name in ("trim_threshold", "mmap_threshold")):
        return False
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # pragma: no cover - glibc always has mallopt
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_MAX)
                and mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD))
