"""The loop pipeline: place-recognition candidates, registration, refinement, verification.

`candidates` finds keyframes that resemble a new one (`DescriptorDatabase`), `book` keeps which
pairs were verified (`LoopBook`), `registration` gives the coarse relative pose of a pair,
`refinement` refines it by rendering (`PoseRefiner`, the paper's relative pose estimation),
`verification` accepts or rejects it (`LoopRecord`), and `pipeline` chains them per new
keyframe (`LoopPipeline`, driven by the back end). docs/loops.md describes each stage.

`PoseRefiner` is imported on first use: it needs torch and the neural field, the candidate
search and the book do not.
"""

from typing import Any

from cpslam.server.loops.book import LoopBook
from cpslam.server.loops.candidates import (
    Candidate,
    DescriptorDatabase,
    LoopCandidate,
    LoopDatabase,
)
from cpslam.server.loops.pipeline import LoopPipeline
from cpslam.server.loops.verification import LoopRecord

__all__ = [
    "Candidate",
    "DescriptorDatabase",
    "LoopBook",
    "LoopCandidate",
    "LoopDatabase",
    "LoopPipeline",
    "LoopRecord",
    "PoseRefiner",
]


def __getattr__(name: str) -> Any:
    if name == "PoseRefiner":
        from cpslam.server.loops.refinement import PoseRefiner

        return PoseRefiner
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
