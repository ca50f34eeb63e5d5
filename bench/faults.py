"""Faults of delivery: what each one loses (must be nothing) and the joint ATE against a
fault-free run.

    python bench/faults.py                      # every fault, 7-Scenes kitchen, tiny preset
    python bench/faults.py --quick              # fewer frames, (f) left out
    python bench/faults.py --only none agent_resume --json /tmp/f.json
    python bench/faults.py --seeds 0 1 2        # in-process faults over three seeds too

Two agents stream overlapping halves of ../shared/data/7scenes-kitchen-0-299 (so they merge
early) to one server. Faults (a)-(e) run in one process on the in-memory bus, driven in
lock-step as ``cpslam run`` (`run.schedule` lockstep, one torch thread, fixed seeds, a virtual
clock): the fault-free run is reproducible and each fault differs from it only by the fault.
Each fault hits agent 1 (or its link) at the middle of the stream (`--fault-at`):

- agent_resume (a): agent 1 stops and restarts with the same id with ``--resume`` (its state.pt
  and link.pt), after its last frame was published and before the server read it;
- agent_refused (b): the same without ``--resume`` first: `run_networked` against the server is
  refused (exit code 5) and the server's record of the first incarnation is compared before and
  after; then it restarts with ``--resume`` so the run can finish;
- server_restart (c): the server stops with frames of both agents still queued, and restarts
  from its durable state (server_state.pt); the agents see its token come back and resend;
- server_fresh (g): the same, but the server starts without its state (a new state id): the
  agents stream their whole state again as new incarnations;
- agent_msg_lost (d): one agent -> server message never arrives (the next one agent 1 sends);
- update_lost (e): one server -> agent update never arrives (the next one to agent 1);
- partition (f): `faults_netns.py`: real processes in network namespaces, agent 0's link down
  for ~10 s; only where namespaces can be made (root, iproute2), skipped with the reason.

"Lost", per agent, at the end: the frames, keyframes and own map points the agent holds that
the server does not (and points the server holds that the agent removed), frame rows missing
from the final global trajectory, messages left unacknowledged, messages the server dropped
(other than the refused incarnation's; decoder weights counted apart, as the agent's later
weights replace them: `decoder_stale` says whether the server ends without the agent's newest),
and foreign points the server believes delivered that the agent does not hold. Joint ATE:
se3-aligned RMSE of both final global trajectories against ground truth
(`cpslam.run.evaluate_run`), and its ratio to the fault-free run. A fault changes when things
happen, and a two-agent run's ATE moves with that as it moves with the seed; `--seeds` runs the
in-process scenarios under each seed and reports, per fault, the mean joint ATE over the seeds
against the fault-free mean (`over_seeds`), beside the fault-free runs' own spread.
A scenario is one function in `SCENARIOS`: called at each frame (after the agents published
it, before the server reads it), it injects its fault.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
import time
from pathlib import Path
from typing import Any

from benchinfo import bench_header
from fault_run import FaultRun, LoseNext, losses, nothing_lost
from faults_netns import partition
from odometry_runs import KITCHEN

ROOT = Path(__file__).resolve().parents[1]
SETS = ["mapping.iters_first=30", "run.schedule=lockstep", "run.num_threads=1"]
# In process the clock is virtual: a lost message is resent one (virtual) second later.
IN_PROCESS_SETS = ["transport.resend_after_s=1.0", "transport.backend=memory"]
FRAMES = "0:90:3,30:120:3"
QUICK_FRAMES = "0:45:3,15:60:3"
AGENT = "1"  # the agent each fault hits

# ----------------------------------------------------------------------------- scenarios
# Each is called at every frame t after the agents published it and before the server reads
# it; `at` is the fault's frame.


def none(run: FaultRun, t: int, at: int) -> None:
    """Fault-free."""


def agent_resume(run: FaultRun, t: int, at: int) -> None:
    """(a) agent 1 stops after frame `at` was published (unread) and resumes."""
    if t == at:
        state = run.stop_agent(AGENT)
        run.start_agent(AGENT, run.seqs[int(AGENT)], resume=state)
        run.notes["resumed_at_frame"] = t


def agent_refused(run: FaultRun, t: int, at: int) -> None:
    """(b) agent 1 stops; a restart without --resume is refused; then it resumes."""
    if t != at:
        return
    state = run.stop_agent(AGENT)
    run.barrier.wait()
    run.server.poll()  # what it had published is in before the comparison
    before = _record(run.server, AGENT)
    code, dropped = _refused_run(run)
    after = _record(run.server, AGENT)
    run.notes.update(
        refused_exit_code=code,
        first_incarnation_intact=before == after,
        refused_messages_dropped=dropped,
    )
    run.start_agent(AGENT, run.seqs[int(AGENT)], resume=state)


def server_restart(run: FaultRun, t: int, at: int) -> None:
    """(c) both agents published frame `at`; the server stops unread and restarts."""
    if t == at:
        run.restart_server()


def server_fresh(run: FaultRun, t: int, at: int) -> None:
    """(g) both agents published frame `at`; the server stops unread and restarts without its
    state: the agents see a new state id and stream everything again as new incarnations."""
    if t == at:
        run.restart_server(keep_state=False)


def agent_msg_lost(run: FaultRun, t: int, at: int) -> None:
    """(d) the next message agent 1 sends never arrives."""
    if t == at:
        node = run.agents[AGENT]
        node.bus = LoseNext(
            node.bus,
            lambda key: (
                "/agent/" in key
                and key.rsplit("/", 1)[-1] in ("keyframe", "submap", "decoder", "frames")
            ),
        )
        run.notes["lossy"] = node.bus


def update_lost(run: FaultRun, t: int, at: int) -> None:
    """(e) the next server update to agent 1 never arrives."""
    if t == at:
        run.server.bus = LoseNext(
            run.server.bus, lambda key: key.endswith(f"/server/agent/{AGENT}/update")
        )
        run.notes["lossy"] = run.server.bus


SCENARIOS = {
    "none": none,
    "agent_resume": agent_resume,
    "agent_refused": agent_refused,
    "server_restart": server_restart,
    "server_fresh": server_fresh,
    "agent_msg_lost": agent_msg_lost,
    "update_lost": update_lost,
}


def _record(server: Any, aid: str) -> tuple:
    """What the server holds of agent `aid`, comparable by ==."""
    with server._lock:  # noqa: SLF001 - bench only
        rec = server.backend.registry.agents[aid]
        return (
            rec.incarnation,
            rec.seq_floor,
            tuple(sorted(rec.frames)),
            tuple((k, r.T_own_kf.tobytes()) for k, r in sorted(rec.keyframes.items())),
            rec.points.ids.tobytes(),
            rec.points.xyz.tobytes(),
        )


def _refused_run(run: FaultRun) -> tuple[int, int]:
    """`run_networked` of agent 1 as a new incarnation while the server polls on a thread;
    returns its exit code and the server's count of dropped messages of that incarnation."""
    from cpslam.agent.daemon import run_networked

    stop = threading.Event()
    registry = run.server.backend.registry

    def serve() -> None:
        while not stop.is_set():
            if not run.server.poll():
                stop.wait(0.02)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        code = run_networked(
            run.cfg,
            run.seqs[int(AGENT)],
            AGENT,
            run.run_dir / "refused",
            "cpu",
            wait_timeout_s=30.0,
            ack_timeout_s=30.0,
            show_progress=False,
            bus=run.bus(),
        )
    finally:
        stop.set()
        thread.join(timeout=60)
    return int(code), int(registry.agents[AGENT].dropped.get("another incarnation", 0))


# ----------------------------------------------------------------------------- accounting


def run_scenario(name: str, cfg: Any, seqs: list, out: Path, at: int) -> dict:
    from cpslam.run import CollabRun, evaluate_run

    inject = SCENARIOS[name]
    t0 = time.perf_counter()
    run = FaultRun(cfg, seqs, out / name)
    try:
        for t in range(max(len(s) for s in seqs)):
            run.step(t, lambda r, t: inject(r, t, at))
        final = run.finish()
        lost = losses(run, final)
        server_drops = dict(run.server.dropped)
    finally:
        run.close()
    evaluation = evaluate_run(CollabRun(run.run_dir, run.ids, final, {}, 0.0), seqs)
    notes = {k: v for k, v in run.notes.items() if k != "lossy"}
    if "lossy" in run.notes:
        notes["lost_key"] = run.notes["lossy"].lost_key
    return {
        "fault_at_frame": at,
        "lost": lost,
        "server_bus_dropped": server_drops,
        "merged": evaluation.get("merged"),
        "joint_ate_m": evaluation.get("global_joint_se3_rmse_m"),
        **notes,
        "wall_s": round(time.perf_counter() - t0, 1),
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seq", type=Path, default=KITCHEN, help="sequence of both agents")
    ap.add_argument(
        "--frames",
        default=None,
        help=f"the agents' frame slices, comma-separated (default {FRAMES})",
    )
    ap.add_argument("--preset", default="tiny")
    ap.add_argument(
        "--set", action="append", default=[], dest="sets", help="config override a.b=value (repeat)"
    )
    ap.add_argument("--seed", type=int, default=0, help="run.seed")
    ap.add_argument("--seeds", type=int, nargs="+", default=None,
                    help="also run the in-process scenarios under these run.seed values and "
                         "report the means over them (the first is the main run)")
    ap.add_argument(
        "--fault-at",
        type=int,
        default=None,
        help="frame (per agent) of the fault (default: the middle)",
    )
    ap.add_argument(
        "--only",
        nargs="+",
        choices=[*SCENARIOS, "partition"],
        default=None,
        help="these scenarios only (the fault-free one always runs)",
    )
    ap.add_argument("--quick", action="store_true", help=f"frames {QUICK_FRAMES}, no (f)")
    ap.add_argument("--partition-s", type=float, default=10.0, help="(f): link down this long")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-faults")
    ap.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    import torch

    from cpslam.agent.standalone import open_for_config
    from cpslam.common.config import load_config

    torch.set_num_threads(1)
    frames = (args.frames or (QUICK_FRAMES if args.quick else FRAMES)).split(",")
    seeds = args.seeds or [args.seed]
    args.seed = seeds[0]
    faults = [n for n in (args.only or SCENARIOS) if n not in ("none", "partition")]
    names = ["none", *faults] if faults or not args.only or "none" in args.only else []
    report: dict = {
        **bench_header("faults", sys.argv if argv is None else ["bench/faults.py", *argv]),
        "seq": str(args.seq),
        "frames": frames,
        "preset": args.preset,
        "sets": [*SETS, *IN_PROCESS_SETS, *args.sets, f"run.seed={args.seed}"],
        "scenarios": {},
    }
    by_seed: dict[int, dict] = {}
    for seed in seeds:
        sets = [*SETS, *IN_PROCESS_SETS, *args.sets, f"run.seed={seed}"]
        cfg = load_config(args.preset, overrides=sets, env={})
        seqs = [open_for_config(cfg, args.seq, frames=f) for f in frames]
        at = args.fault_at if args.fault_at is not None else min(len(s) for s in seqs) // 2
        rows = report["scenarios"] if seed == seeds[0] else {}
        for name in names:
            row = run_scenario(name, cfg, seqs, args.out / f"seed{seed}", at)
            row["nothing_lost"] = nothing_lost(row)
            rows[name] = row
            base = rows["none"]["joint_ate_m"]
            if base and row["joint_ate_m"] is not None:
                row["ate_ratio"] = round(row["joint_ate_m"] / base, 4)
            _line(f"{name} (seed {seed})", row)
        by_seed[seed] = {n: {"joint_ate_m": r["joint_ate_m"], "nothing_lost": r["nothing_lost"]}
                         for n, r in rows.items()}
    if len(seeds) > 1:
        report["by_seed"] = by_seed
        report["over_seeds"] = over_seeds(by_seed)
    if not args.quick and (args.only is None or "partition" in args.only):
        report["partition"] = partition(
            args.seq,
            frames,
            args.preset,
            args.partition_s,
            args.out / "partition",
            args.seed,
            [*SETS, *args.sets],
        )
        _line("partition", report["partition"])
    text = json.dumps(report, indent=2, default=float)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "faults.json").write_text(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text)


def over_seeds(by_seed: dict[int, dict]) -> dict:
    """Per scenario: mean joint ATE over the seeds, its ratio to the fault-free mean, the
    per-seed ratios and whether nothing was lost under any seed."""
    import numpy as np

    out = {}
    names = next(iter(by_seed.values())).keys()
    for name in names:
        ates = [r[name]["joint_ate_m"] for r in by_seed.values()]
        base = [r["none"]["joint_ate_m"] for r in by_seed.values()]
        if any(a is None for a in [*ates, *base]):
            continue
        out[name] = {"ate_mean_m": float(np.mean(ates)),
                     "ratio_of_means": round(float(np.mean(ates) / np.mean(base)), 4),
                     "ratios": [round(a / b, 4) for a, b in zip(ates, base, strict=True)],
                     "nothing_lost": all(r[name]["nothing_lost"] for r in by_seed.values())}
    none = [r["none"]["joint_ate_m"] for r in by_seed.values()]
    if "none" in out and all(a is not None for a in none):
        out["none"]["spread"] = round(float(max(none) / min(none)), 4)  # max / min over seeds
    return out


def _line(name: str, row: dict) -> None:
    ate = row.get("joint_ate_m")
    sys.stdout.write(
        f"{name:<16} lost nothing: {row.get('nothing_lost', row.get('skipped'))}  "
        f"joint ATE {'-' if ate is None else f'{100 * ate:.2f} cm'}  ratio "
        f"{row.get('ate_ratio', '-')}  {row.get('wall_s', 0):.0f} s\n"
    )
    sys.stdout.flush()


if __name__ == "__main__":
    main()
