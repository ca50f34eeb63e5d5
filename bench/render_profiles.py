"""Renderers for docs/results.md: the odometry's CPU-time profile (`bench/stage_profile.py`)
and one-setting-at-a-time sweeps of its knobs (`knobs` reports)."""

from __future__ import annotations

from render_systems import _table


def _stage_profile(report: dict) -> str:
    """Per phase and stage: CPU seconds per frame, per call, calls per frame and share of the
    phase, for the frames after the first; the first frame's totals below."""
    per, first = report["per_frame"], report["first_frame"]
    n = report["frames"] - 1
    height, width = report["resolution"]
    rows = [("phase", "stage", "CPU s/frame", "ms/call", "calls/frame", "share of phase")]
    for phase in ("tracking", "mapping", "other"):
        entry = per.get(phase)
        if entry is None:
            continue
        rows.append((f"**{phase}**", "", f"**{entry['s_per_frame']:.3f}**", "", "", ""))
        for stage, row in entry["stages"].items():
            per_call = "-" if row["ms_per_call"] is None else f"{row['ms_per_call']:.1f}"
            rows.append(("", stage, f"{row['s_per_frame']:.3f}", per_call,
                         f"{row['calls_per_frame']:.1f}", f"{100 * row['share_phase']:.0f} %"))
    rows.append(("**total**", "", f"**{per['total_s_per_frame']:.3f}**", "", "", ""))
    overrides = " ".join(report.get("overrides", []))
    return (f"Preset `{report['preset']}`{' with ' + overrides if overrides else ''}, "
            f"{report['threads']} torch thread(s), lock-step, frames 1-{n} at "
            f"{width}x{height}: {report['track_iters_per_frame']:.1f} LM solves and "
            f"{report['map_steps_per_frame']:.1f} mapping steps per frame; CPU time "
            f"(`time.process_time`) per frame.\n\n" + _table(rows)
            + f"\n\nFirst frame (the first mapping call): {first['total_s_per_frame']:.1f} CPU s, "
            f"mapping {first['mapping']['s_per_frame']:.1f}.\n")


def _knobs(report: dict) -> str:
    """One run per setting: accuracy, recovery events and time, the preset's run first."""
    rows = [("setting", "ATE se3 cm", "max error cm", "RPE1 mm / deg", "events s / r / l",
             "s/frame", "after the first", "tracking s/frame", "mapping s/call",
             "first call s")]
    for setting, r in report["runs"].items():
        if "error" in r:
            rows.append((setting, "error", *[""] * 8))
            continue
        ev = r.get("events", {})
        rows.append((setting, r["ate_se3_cm"], r["max_error_cm"],
                     f"{r['rpe1_mm']} / {r['rpe1_deg']}",
                     f"{ev.get('suspect', 0)} / {ev.get('recovered', 0)} / {ev.get('lost', 0)}",
                     r["s_per_frame"], r["s_per_frame_after_first"], r["tracking_s_per_frame"],
                     r["mapping_s_per_call"], r["first_mapping_s"]))
    return _table(rows) + "\n"
