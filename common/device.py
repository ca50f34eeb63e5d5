"""Choose the torch device once, at the command line, and pass it down."""

from __future__ import annotations

import re

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
