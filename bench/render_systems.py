"""docs/results.md's tables of the system benches: the load harness (`scale`), the delivery
faults (`faults`) and the GPU check and profile (`gpu_check`, `gpu_profile`); with the table
helper every renderer uses. `render_results.py` maps each report's ``bench`` to these."""

from __future__ import annotations

from pathlib import Path

__all__ = ["_faults", "_gpu_check", "_gpu_profile", "_scale", "_table"]


def _table(rows: list[tuple]) -> str:
    head, *body = rows
    lines = ["| " + " | ".join(map(str, head)) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(map(str, r)) + " |" for r in body]
    return "\n".join(lines)


def _scale(report: dict) -> str:
    rows = [("agents", "msgs/s", "server CPU", "poll worst / p99 s", "max queue", "peak RSS MB",
             "merges (last at s)", "slowest merge s", "verify s", "loops acc./found (skipped)",
             "largest group", "joint ATE m", "replay s", "resent")]
    keys_rows = [("agents", "direction", "bytes per agent by key")]
    for r in report["runs"]:
        last = r["merged_at_s"][-1] if r["merged_at_s"] else "-"
        rows.append((r["agents"], r["messages_per_s"], r["server_cpu_share"],
                     f"{r['poll_worst_s']} / {r['poll_p99_s']}", r["max_queue_depth"],
                     r["peak_rss_mb"], f"{r['merges']} ({last})", r.get("merge_worst_s", "-"),
                     r["loop_verification_s"],
                     f"{r['loops_accepted']}/{r['loops_found']} ({r.get('loops_skipped', 0)})",
                     f"{r['largest_group']}/{r['agents']}", r["joint_ate_m"],
                     r["replay_wall_s"], r.get("resent", "-")))
        for direction in ("from_agent", "to_agent"):
            cells = r["bytes_per_agent"][direction]
            keys_rows.append((r["agents"], direction.replace("_", " "),
                              ", ".join(f"{k} {v}" for k, v in cells.items())))
    sets = report.get("server_sets") or []
    server = f" (server with `{' '.join(sets)}`)" if sets else ""
    return (f"One recorded agent ({report['sequence']}, {report.get('frames') or '-'} frames, "
            f"tiny preset) replayed as N agents on the {report['clock']} clock at speed "
            f"{report['speed']}, over Zenoh TCP to a `cpslam-server` process{server} "
            "(docs/scale.md). "
            "Server CPU: share of one core over the replay; resent: messages the replicas "
            "published again, unacknowledged `transport.resend_after_s` after sending; slowest "
            "merge: the longest from a merging loop's verification to its members' updates, "
            "the sum of its timed stages (`merges[].stages` in `metrics.json`).\n\n"
            + _table(rows) + "\n\n" + _table(keys_rows) + "\n")


def _faults(report: dict) -> str:
    rows = [("fault", "nothing lost", "frames / keyframes / points lost (both agents)",
             "unacked", "dropped", "resent", "joint ATE cm", "vs fault-free", "note")]

    def row(name: str, r: dict, note: str = "") -> tuple:
        lost = r["lost"].values()
        total = {k: sum(a.get(k, 0) for a in lost) for k in
                 ("frames_lost", "keyframes_lost", "points_lost", "points_stale",
                  "unacknowledged", "dropped_by_server", "resent", "decoders_dropped",
                  "decoder_stale")}
        ate = r.get("joint_ate_m")
        return (name, r["nothing_lost"],
                f"{total['frames_lost']} / {total['keyframes_lost']} / {total['points_lost']} "
                f"(+{total['points_stale']} stale)", total["unacknowledged"],
                f"{total['dropped_by_server']}" + (f" (+{total['decoders_dropped']} decoder, "
                                                   f"{total['decoder_stale']} stale)"
                                                   if total["decoders_dropped"] else ""),
                total["resent"],
                "-" if ate is None else f"{100 * ate:.2f}", r.get("ate_ratio", "-"), note)

    for name, r in report["scenarios"].items():
        note = ""
        if "refused_exit_code" in r:
            note = (f"restart without --resume: exit {r['refused_exit_code']}, first "
                    f"incarnation intact: {r['first_incarnation_intact']}, "
                    f"{r['refused_messages_dropped']} message(s) of it dropped")
        elif "server_restored" in r:
            note = f"restored from its state: {r['server_restored']}"
            if r.get("stream_restarts"):
                note += (", agents streamed afresh: "
                         + ", ".join(sorted(r["stream_restarts"])))
        elif "lost_key" in r:
            note = f"lost: `{r['lost_key']}`"
        rows.append(row(name, r, note))
    part = report.get("partition")
    if part and "skipped" in part:
        rows.append(("partition", "skipped", part["skipped"], "", "", "", "", "", ""))
    elif part:
        p = part["partitioned"]
        rows.append(row("partition", {**p, "nothing_lost": part["nothing_lost"],
                                      "ate_ratio": part.get("ate_ratio")},
                        f"{part['partition_s']:g} s, real processes; their fault-free run: "
                        f"{100 * part['fault_free_joint_ate_m']:.2f} cm"))
    at = next(iter(report["scenarios"].values()), {}).get("fault_at_frame")
    seeds = ""
    if report.get("over_seeds"):
        seed_rows = [("fault", "nothing lost (every seed)", "joint ATE cm, mean",
                      "mean vs fault-free mean", "per seed vs fault-free")]
        for name, r in report["over_seeds"].items():
            seed_rows.append((name, r["nothing_lost"], f"{100 * r['ate_mean_m']:.2f}",
                              r["ratio_of_means"], ", ".join(f"{x:g}" for x in r["ratios"])))
        spread = report["over_seeds"].get("none", {}).get("spread", "-")
        seeds = (f"\n\nThe in-process faults under run seeds {', '.join(report['by_seed'])} "
                 f"(the first is the table above); the fault-free runs' own largest / smallest "
                 f"joint ATE over the seeds: {spread}.\n\n" + _table(seed_rows))
    return (f"Preset `{report['preset']}`, frames `{', '.join(report['frames'])}` of "
            f"`{Path(report['seq']).name}` as two agents; each fault hits agent 1 at its frame "
            f"{at}; in process, lock-step, one torch thread (partition: real processes in "
            "network namespaces, against a fault-free run of the same processes). Lost: what "
            "the agents hold that the server does not; *dropped*: messages the server dropped "
            "(decoder weights apart: the agent's later weights replace them; *stale*: the "
            "server does not end with the agent's newest); *vs fault-free*: joint ATE ratio."
            "\n\n"
            + _table(rows) + seeds + "\n")


def _gpu_check(report: dict) -> str:
    cols = ("preset", "sequence", "frames", "size", "track s/f", "map s/call", "map s/iter",
            "first map s", "e2e s/f after 1st", "GPU alloc GiB", "GPU reserved GiB", "ATE cm",
            "status")
    rows = [cols] + [tuple("-" if r.get(c) is None else r[c] for c in cols)
                     for r in report["table"]]
    return ("The odometry front end (`bench/odometry.py --loops off`, one run per preset and "
            "sequence, each within its own time budget: frames done of those asked) on CUDA, "
            "beside the CP-SLAM paper's RTX 3090 figures (docs/gpu.md).\n\n"
            + _table(rows) + "\n")


def _gpu_profile(report: dict) -> str:
    waits = report["host_waits_per_frame"]
    head = (f"`{report['preset']}` on {report['device']}, frames 1..{report['frames'] - 1} "
            f"profiled (overrides {', '.join(report['overrides']) or 'none'}): "
            f"{report['wall_s_per_frame']:.2f} s wall per frame, "
            f"{report['lm_iters_per_frame']:.0f} LM iterations, "
            f"{report['host_ms_per_frame']:.0f} ms host and "
            f"{report['device_ms_per_frame']:.0f} ms device time (self, all operators), "
            f"{report['kernel_launches_per_frame']:.0f} kernel launches, host waits "
            + ", ".join(f"`{k}` {v:.0f}" for k, v in waits.items()) + " per frame.")
    rows = [("operator (top 10 by device time)", "calls / frame", "host ms / frame",
             "device ms / frame")]
    rows += [(r["op"][:70], round(r["calls_per_frame"], 1),
              round(r["self_host_ms_per_frame"], 2), round(r["self_device_ms_per_frame"], 2))
             for r in report["by_device_time"][:10]]
    return head + "\n\n" + _table(rows) + "\n"


def _pose_graph_cost(report: dict) -> str:
    rows = [("agents", "keyframes per agent", "nodes", "edges", "loops", "build s",
             "optimise s", "LM iterations", "false loops flagged", "RMSE before / after cm")]
    for r in report["rows"]:
        rows.append((r["agents"], r["keyframes_per_agent"], r["nodes"], r["edges"], r["loops"],
                     r["build_s"], r["optimise_s"], r["iterations"], r["outlier_loops"],
                     f"{100 * r['rmse_before_m']:.2f} / {100 * r['rmse_after_m']:.2f}"))
    return (f"Preset `{report['preset']}`'s `pose_graph` section; synthetic tracks with a loop "
            f"every {report['loop_every']} keyframes to the next agent and one within the "
            "agent (5 % of them false); best of the repeats.\n\n" + _table(rows) + "\n")
