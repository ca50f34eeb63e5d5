"""What logging to Rerun (`run.rerun: save`) costs a standalone agent: seconds and CPU seconds
per frame with and without it, on one synthetic sequence, the two settings alternating over
`--repeats` runs each in this one process (so the machine's load hits both alike).

The agent runs in lock-step (`run.schedule=lockstep`), so both settings do the same SLAM work
bit for bit and differ only by the logging; the printed ratio is the median of
with / without over the repeats. Because that ratio carries the machine's noise, the runs
with logging also time the recorder's own calls (wall and CPU seconds inside them, per
frame): the part of a frame that logging takes on the agent's thread, whatever the load.

Usage: python bench/rerun_overhead.py [--frames 30] [--repeats 3] [--preset cpu]
           [--json bench/results/rerun-overhead.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchinfo import bench_header  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    import torch

    from cpslam.agent.standalone import run_standalone
    from cpslam.common.config import load_config
    from cpslam.common.datasets import open_sequence
    from cpslam.tools.synth import generate
    from cpslam.tools.view.agent_log import AgentRecorder

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory(prefix="bench-rerun-") as tmp:
        data = generate(Path(tmp) / "room", scene="room", agents=1, frames=args.frames,
                        width=320, height=240, seed=0, loop=True)
        seq = open_sequence(data.agent_dirs[0])
        runs: dict[str, list[dict]] = {"off": [], "save": []}
        for repeat in range(args.repeats):
            for mode in ("off", "save"):
                cfg = load_config(args.preset, env={}, overrides=[
                    "run.schedule=lockstep", "run.num_threads=1",
                    f"run.rerun={'null' if mode == 'off' else mode}"])
                out = Path(tmp) / f"{mode}-{repeat}"
                recorder = AgentRecorder.from_config(cfg.run, "0", out / "agent_0")
                inside = [0.0, 0.0]

                def on_frame(*args, recorder=recorder, inside=inside) -> None:
                    w, c = time.perf_counter(), time.thread_time()
                    recorder(*args)
                    inside[0] += time.perf_counter() - w
                    inside[1] += time.thread_time() - c

                t0, c0 = time.perf_counter(), time.process_time()
                result = run_standalone(cfg, seq, out, "cpu", show_progress=False,
                                        on_frame=on_frame if recorder is not None else None)
                if recorder is not None:
                    recorder.close()
                wall, cpu = time.perf_counter() - t0, time.process_time() - c0
                rrd = out / "agent_0" / "live.rrd"
                runs[mode].append({
                    "s_per_frame": round(wall / result.frames_done, 4),
                    "cpu_s_per_frame": round(cpu / result.frames_done, 4),
                    "rrd_mb": round(rrd.stat().st_size / 1e6, 3) if rrd.exists() else None,
                    "recorder_s_per_frame": round(inside[0] / result.frames_done, 5),
                    "recorder_cpu_s_per_frame": round(inside[1] / result.frames_done, 5),
                })
                print(f"repeat {repeat} {mode:>4}: {runs[mode][-1]}", flush=True)
    ratios = {key: round(statistics.median(
        s[key] / o[key] for s, o in zip(runs["save"], runs["off"], strict=True)), 3)
        for key in ("s_per_frame", "cpu_s_per_frame")}
    ratios["recorder_share"] = round(statistics.median(
        s["recorder_s_per_frame"] / s["s_per_frame"] for s in runs["save"]), 4)
    report = {**bench_header("rerun_overhead", sys.argv), "preset": args.preset,
              "frames": args.frames, "repeats": args.repeats, "runs": runs,
              "ratio_save_over_off": ratios}
    print(json.dumps(ratios))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
