"""Pictures of an ATE evaluation: top view of GT vs aligned estimate, and error over time."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from cpslam.tools.eval.ate import AteResult

logger = logging.getLogger(__name__)

_AXES = "xyz"


def plot_ate(
    results: AteResult | Sequence[AteResult],
    path: str | Path,
    title: str | None = None,
    labels: Sequence[str] | None = None,
) -> Path:
    """Write a PNG: left the trajectories seen from above, right the position error over time.

    ``results`` is one ``AteResult`` or several (e.g. the ``parts`` of a joint evaluation,
    one colour each, ``labels`` naming them). The top view shows the plane of the two world
    axes along which the ground truth extends most, so it works whatever axis is "up".
    """
    # matplotlib.figure.Figure draws with the Agg canvas without touching pyplot or the
    # global backend, so this works headless and leaves a caller's backend alone.
    from matplotlib.figure import Figure

    parts = [results] if isinstance(results, AteResult) else list(results)
    if not parts:
        raise ValueError("plot_ate: nothing to plot")
    if labels is None:
        labels = ["estimate"] if len(parts) == 1 else [f"agent {i}" for i in range(len(parts))]
    if len(labels) != len(parts):
        raise ValueError(f"plot_ate: {len(labels)} labels for {len(parts)} trajectories")

    a, b = top_view_axes(np.concatenate([p.gt_xyz for p in parts]))
    t0 = min(float(p.stamps.min()) for p in parts)
    fig = Figure(figsize=(12, 5), layout="constrained")
    ax_top, ax_err = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1, 1.3]})
    colours = [f"C{i}" for i in range(len(parts))]
    for i, (part, label, colour) in enumerate(zip(parts, labels, colours, strict=True)):
        order = np.argsort(part.stamps, kind="stable")
        gt, est = part.gt_xyz[order], part.est_xyz[order]
        ax_top.plot(gt[:, a], gt[:, b], color="0.2", ls="--", lw=1.2,
                    label="ground truth" if i == 0 else None)  # fmt: skip
        ax_top.plot(est[:, a], est[:, b], color=colour, lw=1.2, label=label)
        ax_top.plot(gt[0, a], gt[0, b], "o", color="0.2", ms=5)
        ax_top.plot(est[0, a], est[0, b], "o", color=colour, ms=5)
        ax_err.plot(part.stamps[order] - t0, 100.0 * part.trans_err[order], color=colour,
                    lw=1.0, label=f"{label}: RMSE {100.0 * part.rmse:.2f} cm")  # fmt: skip
        ax_err.axhline(100.0 * part.rmse, color=colour, ls=":", lw=1.0)
    ax_top.set_xlabel(f"{_AXES[a]} [m]")
    ax_top.set_ylabel(f"{_AXES[b]} [m]")
    ax_top.set_aspect("equal", adjustable="datalim")
    ax_top.set_title(f"top view ({_AXES[a]}–{_AXES[b]} plane), {parts[0].align} alignment")
    ax_top.grid(alpha=0.3)
    ax_top.legend(loc="best", fontsize="small")
    ax_err.set_xlabel("time since first pose [s]")
    ax_err.set_ylabel("position error [cm]")
    ax_err.set_title("absolute trajectory error")
    ax_err.set_ylim(bottom=0.0)
    ax_err.grid(alpha=0.3)
    ax_err.legend(loc="best", fontsize="small")
    if title:
        fig.suptitle(title)

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, format="png")
    logger.info("wrote %s", path)
    return path


def top_view_axes(xyz: np.ndarray) -> tuple[int, int]:
    """Indices (ascending) of the two world axes along which ``xyz [N, 3]`` extends most."""
    extent = np.ptp(np.asarray(xyz, dtype=np.float64), axis=0)
    a, b = sorted(np.argsort(-extent, kind="stable")[:2].tolist())
    return a, b
