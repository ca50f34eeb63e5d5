"""The bench scripts stay runnable: each parses its arguments and prints its usage, and the
odometry bench's seed summary is what its table reads."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
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


def test_odometry_bench_rpe_leaves_out_spans_longer_than_the_run(
        capsys: pytest.CaptureFixture[str]) -> None:
    sys.path.insert(0, str(BENCH))
    try:
        import odometry as bench
    finally:
        sys.path.remove(str(BENCH))
    stamps = np.arange(8, dtype=np.float64)
    poses = np.repeat(np.eye(4)[None], 8, axis=0)
    poses[:, 0, 3] = 0.01 * stamps  # 1 cm per frame
    est = poses.copy()
    est[:, 0, 3] *= 1.1  # 1 mm per frame too far
    out = bench._rpe(stamps, poses, stamps, est)
    assert out["rpe1_mm"] == pytest.approx(1.0) and "rpe10_mm" not in out
    report = {"seeds": [0], "paper_rtx3090": bench.PAPER,
              "synthetic": {"resolution": "8x8", "ate_se3_cm": 0.1, "mean_s_per_frame": 1.0,
                            "tracking_s_per_frame": 0.5,
                            "mapping_s_per_call": 1.0, "points": 3, "per_seed": [{}], **out}}
    bench.print_table(report)  # prints "-" for the missing span instead of failing
    row = next(line for line in capsys.readouterr().out.splitlines() if "cpslam" in line)
    assert "1.0/" in row and " - " in row
