"""The GPU check's table: bench/odometry.py's JSON reports (one per preset and sequence) side
by side with the CP-SLAM paper's figures, printed and written as one JSON.

Per run: frames done (of those asked: runs stop at their time budget), tracking seconds per
frame, mapping seconds per mapping call and per optimisation step (the first mapping's steps
too, which every run reaches), end-to-end seconds per frame (with and without the first
mapping), peak GPU memory (allocated by tensors, reserved by torch's caching allocator), and
ATE (se3 for the real frames, origin-aligned for synthetic ones, as the paper reports).
The paper's row: tracking 0.30 s per frame and 10.1 s per mapped frame on an RTX 3090, and
7.70 GiB of GPU memory (measured by others running the official code, nvidia-smi's figure:
compare it with the reserved column plus the CUDA context, about 0.5 GiB).

A report with "failed" instead of runs (bench/gpu_check.sh writes one for a run that did not
finish) is listed with its reason.

Usage: python bench/gpu_report.py REPORT.json [...] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from odometry_runs import PAPER  # noqa: E402

COLUMNS = ("preset", "sequence", "frames", "size", "track s/f", "map s/call", "map s/iter",
           "first map s", "e2e s/f", "e2e s/f after 1st", "GPU alloc GiB", "GPU reserved GiB",
           "ATE cm", "status")


def rows(reports: list[dict]) -> list[dict]:
    """One row per run of every report (or one per failed report)."""
    out = []
    for report in reports:
        preset = report.get("preset", "?")
        if "failed" in report:
            out.append({"preset": preset, "sequence": report.get("only", "?"),
                        "status": report["failed"]})
            continue
        if not report.get("runs") and report.get("real_skipped"):
            out.append({"preset": preset, "sequence": "real", "status": report["real_skipped"]})
        for run in report.get("runs", []):
            row = {"preset": preset, "sequence": run["sequence"]}
            if "error" in run:
                row["status"] = "error: " + run["error"].strip().splitlines()[-1][:120]
                out.append(row)
                continue
            real = run.get("kind") == "real"
            ate_key = "ate_se3_cm" if real else "ate_origin_cm"
            row.update({
                "frames": f"{run['frames']}/{run.get('frames_asked', run['frames'])}",
                "size": run.get("resolution"),
                "track s/f": run.get("tracking_s_per_frame"),
                "map s/call": run.get("mapping_s_per_call"),
                "map s/iter": run.get("mapping_s_per_iter")
                or run.get("first_mapping_s_per_iter"),
                "first map s": run.get("first_mapping_s"),
                "e2e s/f": run.get("s_per_frame"),
                "e2e s/f after 1st": run.get("s_per_frame_after_first"),
                "GPU alloc GiB": _gib(run.get("peak_gpu_memory_mb")),
                "GPU reserved GiB": _gib(run.get("peak_gpu_reserved_mb")),
                "ATE cm": run.get(ate_key),
                "status": run.get("accuracy_error", "ok")[:120],
            })
            out.append(row)
    return out


def paper_row() -> dict:
    return {"preset": "paper (RTX 3090)", "sequence": "-", "track s/f":
            PAPER["tracking_s_per_frame"], "map s/call": PAPER["mapping_s_per_call"],
            "GPU reserved GiB": PAPER["gpu_memory_gib"], "status": "reference"}


def _gib(mb: float | None) -> float | None:
    return None if mb is None else round(mb / 1024, 2)


def print_table(table: list[dict]) -> None:
    cells = [list(COLUMNS)] + [[_cell(r.get(c)) for c in COLUMNS] for r in table]
    widths = [max(len(row[i]) for row in cells) for i in range(len(COLUMNS))]
    for row in cells:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip())


def _cell(value) -> str:
    return "-" if value is None else str(value)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reports", type=Path, nargs="+", help="bench/odometry.py JSON files")
    parser.add_argument("--json", type=Path, default=None, help="write the table here")
    args = parser.parse_args()
    reports = []
    for path in args.reports:
        try:
            reports.append(json.loads(path.read_text()))
        except (OSError, json.JSONDecodeError) as error:
            reports.append({"preset": path.stem, "failed": f"{path}: unreadable ({error})"})
    table = rows(reports) + [paper_row()]
    print_table(table)
    machine = next((r["machine"] for r in reports if "machine" in r), None)
    if machine:
        print(f"\nmachine: {machine.get('gpu')} / {machine.get('cpu')}, {machine.get('cores')} "
              f"cores, torch {machine.get('torch')}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        first = next((r for r in reports if "commit" in r), {})
        args.json.write_text(json.dumps({
            "bench": "gpu_check", "command": "bash bench/gpu_check.sh",
            "commit": first.get("commit"), "dirty": first.get("dirty"), "machine": machine,
            "paper_rtx3090": PAPER, "table": table, "reports": reports}, indent=2) + "\n")
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
