"""The bench scripts stay runnable: each parses its arguments and prints its usage, and the
odometry bench's seed summary is what its table reads."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"


@pytest.mark.parametrize("script", sorted(p.name for p in BENCH.glob("*.py")))
def test_bench_script_prints_its_usage(script: str) -> None:
    done = subprocess.run([sys.executable, str(BENCH / script), "--help"], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "usage:" in done.stdout


def test_odometry_bench_summarises_seeds() -> None:
    sys.path.insert(0, str(BENCH))
    try:
        import odometry as bench
    finally:
        sys.path.remove(str(BENCH))
    runs = [{"ate_se3_cm": a, "rpe1_mm": r, "mean_s_per_frame": 1.0, "points": 10}
            for a, r in ((2.0, 5.0), (4.0, 7.0))]
    out = bench._summarise(runs, [0, 1])
    assert out["ate_se3_cm"] == 2.0 and out["points"] == 10  # the first seed at the top
    assert [s["seed"] for s in out["per_seed"]] == [0, 1]
    assert out["mean_over_seeds"]["ate_se3_cm"] == 3.0
    assert out["worst_over_seeds"] == {"ate_se3_cm": 4.0, "rpe1_mm": 7.0}
