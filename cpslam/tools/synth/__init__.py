"""Synthetic RGB-D scenes with ground truth: develop, test and demo without downloads.

`generate(out, scene="room", agents=1, frames=300, ...)` renders a collection in the Replica
layout (see `writer`); `cpslam dataset synth` is its command line (`cli.synth`). The parts:
`scene` (layout and furniture meshes), `texture` (procedural materials), `trajectory`
(hand-held camera paths), `render` (ray casting and depth noise).
"""

from __future__ import annotations

from typing import Any

__all__ = ["SynthResult", "generate"]


def __getattr__(name: str) -> Any:
    # Lazy, so that importing the CLI command does not pull in scipy and OpenCV.
    if name in __all__:
        from cpslam.tools.synth import writer

        return getattr(writer, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
