"""Six agents on one `cpslam-server` process over Zenoh TCP: one agent's wire recording replayed
as six agents, each in a world of its own (the load harness, docs/scale.md). They all end in
one group, nothing is lost, and the run folder is complete."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from daemons import Daemon, finalise, server_args, tum_rows, wait_until

pytestmark = [pytest.mark.loopback, pytest.mark.slow]
pytest.importorskip("open3d")  # the synthetic renderer

FRAMES = 20
AGENTS = 6


def _record(tmp: Path) -> Path:
    """A tiny-preset `cpslam run` of one agent in the synthetic room, link.record on."""
    from cpslam.common.config import load_config, override_config
    from cpslam.common.datasets import open_sequence
    from cpslam.run import run_collab
    from cpslam.tools.synth import generate

    data = generate(tmp / "room", scene="room", frames=FRAMES, width=160, height=120, seed=0)
    cfg = override_config(load_config("tiny"), ["mapping.iters_first=30", "link.record=true"])
    run_collab(cfg, [open_sequence(data.agent_dirs[0])], tmp / "rec", show_progress=False)
    return tmp / "rec" / "agent_0" / "wire.rec"


def _summary(bus, session: str) -> dict:
    from cpslam import protocol
    from cpslam.protocol import Status, keys

    for reply in bus.query(keys.server_status(session), None, timeout_s=5.0):
        try:
            return protocol.decode(reply.payload, expected=Status).summary
        except Exception:  # noqa: BLE001 - an error reply: ask again
            continue
    return {}


def test_six_agents_merge_into_one_group(tmp_path: Path, endpoint: str, daemons) -> None:
    from cpslam.agent.daemon import ServerPresence
    from cpslam.agent.recording import read_recording
    from cpslam.common.bus import open_client
    from cpslam.common.config import load_config, override_config
    from cpslam.common.config.cli import transport_sets
    from cpslam.tools.replay import ReplayAgent, Replica, random_rigid, replay

    recording = read_recording(_record(tmp_path))
    out, s = tmp_path / "run", "six"
    server = Daemon("server", server_args(endpoint, s, out, "--no-report"), tmp_path)
    daemons.append(server)
    cfg = override_config(load_config("tiny"),
                          [*transport_sets(s, None, [endpoint]), "transport.mode=client"])
    buses = [open_client(cfg.transport, 60.0, "six agents", limits=cfg.limits)
             for _ in range(AGENTS + 1)]
    assert all(bus is not None for bus in buses), server.tail()
    try:
        presence = ServerPresence(buses[0], s)
        assert presence.wait(60.0), server.tail()
        presence.close()
        rng = np.random.default_rng(0)
        agents = [ReplayAgent(Replica(f"r{k}", recording, random_rigid(rng)), bus, s,
                              zstd_level=cfg.link.zstd_level).start()
                  for k, bus in enumerate(buses[1:])]
        played = replay(agents, ack_timeout_s=180.0)
        assert played["unacknowledged"] == {}, server.tail()

        def one_group() -> bool:
            for agent in agents:  # answer updates while the server merges
                agent.poll()
            groups = _summary(buses[0], s).get("groups", {})
            return any(len(g["members"]) == AGENTS for g in groups.values())

        wait_until("all six agents in one group", one_group, 400, server, every=0.5)
        for agent in agents:
            assert agent.refused is None
            agent.close()
    finally:
        for bus in buses:
            if bus is not None:
                bus.close()
    finalise(endpoint, s)
    assert server.wait(300) == 0, server.tail()

    metrics = json.loads((out / "metrics.json").read_text())
    assert [len(g["members"]) for g in metrics["groups"]] == [AGENTS]
    # Replicas never apply the server's updates or decoders, so their decoder weights answer
    # no open federated round: the only drops allowed, none of them map data.
    assert set(metrics["dropped"]) <= {"decoder weights for a past round or group"}
    for k in range(AGENTS):
        row = metrics["agents"][f"r{k}"]
        assert row["merged"] and row["frames"] == FRAMES and not row["dropped"]
        assert tum_rows(out / "trajectories" / f"agent_r{k}_global.tum") == FRAMES
    assert (out / "fused_map.ply").is_file() and (out / "pose_graph.g2o").is_file()
