"""What every bench JSON starts with: the command, the commit and the machine, so that a
figure in docs/results.md can be traced to how and where it was measured."""

from __future__ import annotations

import os
import platform
import shlex
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = 1


def bench_header(bench: str, argv: list[str]) -> dict:
    """{"schema", "bench", "command", "commit", "dirty", "machine"}."""
    return {"schema": SCHEMA, "bench": bench,
            "command": "python " + shlex.join([_relative(argv[0]), *argv[1:]]),
            "commit": _git("rev-parse", "--short", "HEAD"),
            "dirty": bool(_git("status", "--porcelain", "--untracked-files=no")),
            "machine": machine()}


def machine() -> dict:
    """CPU model, usable cores, SIMD level, Python and torch versions."""
    import torch

    model, flags = "", set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and not model:
                model = line.split(":", 1)[1].strip()
            elif line.startswith("flags") and not flags:
                flags = set(line.split(":", 1)[1].split())
    except OSError:
        pass
    simd = "amx" if "amx_tile" in flags else "avx512" if "avx512f" in flags else \
        "avx2" if "avx2" in flags else "other"
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cpu": model or platform.processor() or platform.machine(), "cores": cores,
            "simd": simd, "python": platform.python_version(), "torch": torch.__version__,
            "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}


def _git(*args: str) -> str:
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True,
                              timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def _relative(path: str) -> str:
    try:
        return str(Path(path).resolve().relative_to(ROOT))
    except ValueError:
        return path
