"""The in-process harness of bench/faults.py: two agents and the server on one in-memory
network, driven in lock-step as ``cpslam run``, with the hooks a fault needs (stop and resume an
agent, restart the server from its state file, lose one publication), and the accounting of
what each agent produced that the server does not hold."""

from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

LOSS_COUNTS = (
    "frames_lost",
    "trajectory_rows_lost",
    "keyframes_lost",
    "points_lost",
    "points_stale",
    "unacknowledged",
    "dropped_by_server",
)
"""Per-agent counts that must be 0 after any fault."""


def split_drops(dropped: dict[str, int]) -> tuple[dict[str, int], int]:
    """The server's per-agent drop reasons without the refused incarnation's messages and
    without decoder weights, and the count of decoder weights dropped (a delta against a base
    the server no longer holds, e.g. resent after its round closed: decoders are state, the
    agent's next weights replace them; whether the server ends with the agent's newest weights
    is `decoder_stale`)."""
    kept, decoders = {}, 0
    for reason, n in dropped.items():
        if reason.startswith("decoder"):
            decoders += n
        elif reason != "another incarnation":
            kept[reason] = n
    return kept, decoders


class FaultRun:
    """Two (or more) agents and the server on one in-memory network, in lock-step."""

    def __init__(self, cfg: Any, seqs: list, run_dir: Path) -> None:
        import torch

        from cpslam.common.bus import InMemoryNetwork
        from cpslam.common.config import save_config

        self.cfg, self.seqs, self.run_dir = cfg, seqs, run_dir
        self.ids = [str(i) for i in range(len(seqs))]
        # A state file left by an earlier run would be restored: every run starts afresh.
        if run_dir.exists():
            shutil.rmtree(run_dir)
        run_dir.mkdir(parents=True)
        save_config(cfg, run_dir / "config.yaml")
        torch.manual_seed(cfg.run.seed)
        self.clock = [0.0]
        self.period = float(np.median(np.diff(seqs[0].timestamps)))
        self.network = InMemoryNetwork()
        self.state_path = run_dir / "server_state.pt"
        self.notes: dict[str, Any] = {}
        self.unconfirmed: dict[str, int] = {}
        self.buses: list = []
        self.server = self._server()
        self.agents: dict[str, Any] = {}
        self.presence: dict[str, Any] = {}
        self.streams: dict[str, Any] = {}
        for aid, seq in zip(self.ids, seqs, strict=True):
            self.start_agent(aid, seq)

    def bus(self) -> Any:
        from cpslam.common.bus import InMemoryBus

        self.buses.append(InMemoryBus(self.network))
        return self.buses[-1]

    def _server(self) -> Any:
        from cpslam.run import LockstepBarrier
        from cpslam.server.node import ServerNode

        # Every ack waits for a durable state (written in the poll loop, each poll): a server
        # restarted from it has everything it acknowledged.
        server = ServerNode(
            self.cfg,
            self.bus(),
            self.run_dir,
            state_path=self.state_path,
            persist_every_s=0.0,
            persist_background=False,
            now=lambda: self.clock[0],
        ).start()
        self.barrier = LockstepBarrier(server.bus, server.session)
        return server

    def start_agent(self, aid: str, seq: Any, resume: Path | None = None) -> Any:
        from cpslam.agent.daemon import ServerPresence, _answer_server
        from cpslam.agent.node import AgentNode

        bus = self.bus()
        node = AgentNode(self.cfg, seq, bus, aid, self.run_dir, now=lambda: self.clock[0])
        if resume is not None:
            node.resume(resume)
        node.start()
        presence = ServerPresence(bus, self.cfg.transport.session)
        if not presence.wait(30.0):
            raise RuntimeError(f"agent {aid}: no server token on the in-memory bus")
        node.online = presence.settled
        # as `run_networked`: a resumed agent resends its outbox, or streams afresh to a
        # server that lost its state
        _answer_server(node, presence, resend=resume is not None)
        self.agents[aid], self.streams[aid] = node, node.frames()
        self.presence[aid] = presence
        return node

    def stop_agent(self, aid: str) -> Path:
        """The agent's process ends: its outputs (state.pt, link.pt) written, all it had
        published still on its way. Returns its state.pt."""
        node = self.agents.pop(aid)
        node.write_outputs()
        node.close()
        self.presence.pop(aid).close()
        return self.run_dir / f"agent_{aid}" / "state.pt"

    def restart_server(self, keep_state: bool = True) -> None:
        """The server stops with whatever is queued for it unread, and starts again from its
        state file (`keep_state`) or without it. As with a real restart, the agents see its
        token go before the new server's comes."""
        old = self.server.backend.state_id
        self.server.close()
        self.server.bus.close()
        # The token's leave reaches each agent on the bus's dispatcher thread. Past the bound
        # the restart goes on all the same: the new token's join is what the agents answer.
        deadline = time.monotonic() + 5.0
        for pres in self.presence.values():
            pres.wait_for(lambda p: not p.up, max(deadline - time.monotonic(), 0.0))
        if not keep_state:
            for path in self.state_path.parent.glob(self.state_path.name + "*"):
                path.unlink()
        self.server = self._server()
        self.notes["server_restored"] = self.server.restored
        self.notes["server_state_kept"] = self.server.backend.state_id == old

    def exchange(self) -> None:
        """As `cpslam run`: flush, the server handles and steps, flush, agents apply; agents
        resend what is unacknowledged after the server came back or after resend_after_s."""
        from cpslam.agent.daemon import _answer_server

        for aid, node in self.agents.items():  # as `run_networked` between frames
            pres = self.presence[aid]
            restarts = node.restarts
            _answer_server(node, pres)
            if node.restarts > restarts:
                self.notes.setdefault("stream_restarts", {})[aid] = node.restarts
            if pres.settled():
                node.resend_due()
        self.barrier.wait()
        self.server.poll()
        self.barrier.wait()
        for node in self.agents.values():
            node.poll()

    def step(self, t: int, inject: Any = None) -> None:
        """Every agent takes frame t and publishes; `inject(self, t)` runs next, before the
        server reads what they published; then the exchange."""
        for aid, seq in zip(self.ids, self.seqs, strict=True):
            if aid in self.agents and t < len(seq):
                self.agents[aid].step(next(self.streams[aid]))
        if inject is not None:
            inject(self, t)
        self.exchange()
        self.clock[0] += self.period

    def finish(self, max_rounds: int = 50) -> Any:
        """Flush the agents; exchange, the virtual clock moving on so resends and periodic
        updates fall due, until nothing is unacknowledged either way and no update is due;
        note the updates still unconfirmed then (`unconfirmed`); finalise."""
        backend = self.server.backend
        for node in self.agents.values():
            node.flush()
        for _ in range(max_rounds):
            self.exchange()
            self.barrier.wait()  # the agents' last update acks are queued for the server
            pending = any(n.link.outbox for n in self.agents.values()) or any(
                backend.sharing.foreign.pending(a) for a in self.agents
            )
            if not pending and not backend.sharing.due(list(backend.groups.groups.values())):
                break
            self.clock[0] += self.cfg.transport.resend_after_s
        self.server.poll()  # reads those acks
        self.unconfirmed = {a: int(backend.sharing.foreign.pending(a)) for a in self.agents}
        return self.server.finalise()

    def close(self) -> None:
        for node in self.agents.values():
            node.write_outputs()
            node.close()
        for pres in self.presence.values():
            pres.close()
        self.server.close()
        for bus in self.buses:
            bus.close()


class LoseNext:
    """A bus whose next publication on a key `match` accepts never arrives."""

    def __init__(self, bus: Any, match: Any) -> None:
        self._bus, self.match, self.lost_key = bus, match, None

    def publish(self, key: str, payload: bytes) -> None:
        if self.lost_key is None and self.match(key):
            self.lost_key = key
            return
        self._bus.publish(key, payload)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._bus, name)


def losses(run: FaultRun, final: Any) -> dict[str, dict[str, int]]:
    """Per agent: what it produced that the server does not hold (see the docstring)."""
    registry = run.server.backend.registry
    foreign = run.server.backend.sharing.foreign
    rows = {a.agent_id: len(a.stamps) for a in final.agents}
    out = {}
    for aid, node in run.agents.items():
        rec = registry.agents[aid]
        stamps, _ = node.odometry.trajectory()
        pm = node.odometry.point_map
        own = set(pm.point_id[pm.agent_id == 0].tolist())
        held = set(rec.points.ids.tolist())
        missing_foreign = 0
        for source, ids in foreign.delivered(aid).items():
            key = node.link.foreign_index.get(source)
            have = set() if key is None else set(pm.point_id[pm.agent_id == key].tolist())
            missing_foreign += len(set(ids) - have)
        drops, decoders = split_drops(dict(rec.dropped))
        newest = node.link.decoder_base.own_seq  # the agent's newest acknowledged weights
        out[aid] = {
            "frames": len(stamps),
            "frames_lost": len(stamps) - len(rec.frames),
            "trajectory_rows_lost": len(stamps) - rows.get(aid, 0),
            "keyframes": len(node.odometry.keyframes),
            "keyframes_lost": len(set(node.odometry.keyframes.ids()) - set(rec.keyframes)),
            "points": len(own),
            "points_lost": len(own - held),
            "points_stale": len(held - own),
            "unacknowledged": len(node.link.outbox),
            "dropped_by_server": sum(drops.values()),
            "decoders_dropped": decoders,
            "decoder_stale": int(newest is not None and rec.decoder_seq != newest),
            "foreign_points_missing": missing_foreign,
            "updates_unconfirmed": run.unconfirmed[aid],
            "resent": node.link.outbox.resent,
        }
    return out


def nothing_lost(row: dict) -> bool:
    """Every agent's losses are 0 and the injected fault did happen."""
    counts = (*LOSS_COUNTS, "foreign_points_missing", "updates_unconfirmed", "decoder_stale")
    ok = all(a[c] == 0 for a in row.get("lost", {}).values() for c in counts)
    return ok and not row.get("server_bus_dropped") and row.get("lost_key", "") is not None
