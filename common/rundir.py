"""Run folders: one directory per run holding its effective config, outputs and metrics."""

from __future__ import annotations

import json
import resource
import sys
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

SCHEMA_VERSION = 1
"""Version of the JSON files and ``--json`` records cpslam writes for people and tools to
read (report.json, metrics.json, evaluation.json, the `cpslam eval` records; the list is in
docs/evaluation.md): their ``schema_version`` field. Raised when a
field is renamed or removed or its meaning changes; new fields do not raise it."""


def create_run_dir(out: str | Path, name: str | None = None) -> Path:
    """`out/name`, or `out/YYYYmmdd-HHMMSS` when no name is given; created if missing.

    A timestamped folder never reuses an existing one (a suffix is added), so two runs started
    in the same second do not mix their outputs.
    """
    base = Path(out)
    if name:
        run = base / name
    else:
        stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
        run = base / stamp
        suffix = 1
        while run.exists():
            run = base / f"{stamp}-{suffix}"
            suffix += 1
    run.mkdir(parents=True, exist_ok=True)
    return run


def write_json(path: str | Path, data: Any) -> Path:
    """Write JSON with numpy scalars and arrays converted to plain numbers and lists,
    atomically (a crash leaves the old file or the new one, never half of it)."""
    from cpslam.common.durable import write_text_atomic

    return write_text_atomic(path, json.dumps(data, indent=2, default=_to_builtin) + "\n")


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MiB (Linux reports KiB, macOS bytes)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024 * 1024) if sys.platform == "darwin" else peak / 1024


def _to_builtin(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
