"""Traffic figures of a server run: bytes, messages and bytes per second per agent and per key.

The bus counts subscriptions under the subscribed expression (``agent/*/*`` for everything the
agents publish), so `KeyCounter` counts what the server takes off that queue under each
concrete key; what the server sends each agent, its group's decoders included, goes on the
agent's own keys and is counted by the bus. The functions here turn those counts and
`Bus.stats()` into the ``bus`` section of the server's ``metrics.json`` (`bus_metrics`,
documented in docs/daemons.md). Rates come per second of the server's uptime and, where the
agents' frame stamps are known, per second of sensor time (`common.trajectory.sensor_seconds`):
bandwidth that does not depend on how fast this machine processes frames.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping

import numpy as np

from cpslam.common.bounds import OTHER
from cpslam.protocol import keys

__all__ = ["KeyCounter", "PollTimes", "bus_metrics", "traffic_per_agent", "traffic_per_group"]

Table = dict[str, dict[str, int]]
"""{key or agent: {"messages": int, "bytes": int}}"""


class KeyCounter:
    """Messages and bytes per key (one thread counts; `table` returns a copy).

    Keys come from peers: at most `max_keys` are kept, the rest count under "other" (which
    no agent or group key parses as, so per-agent figures skip it).
    """

    def __init__(self, max_keys: int | None = None) -> None:
        self._rows: dict[str, list[int]] = {}
        self.max_keys = max_keys

    def add(self, key: str, nbytes: int) -> None:
        if key not in self._rows and self.max_keys is not None and (
                len(self._rows) >= self.max_keys):
            key = OTHER
        row = self._rows.setdefault(key, [0, 0])
        row[0] += 1
        row[1] += int(nbytes)

    def table(self) -> Table:
        return {k: {"messages": m, "bytes": b} for k, (m, b) in self._rows.items()}


class PollTimes:
    """How long each `ServerNode.poll` took and how many messages waited when it began.

    A message that arrives just after a poll began waits for the whole poll, so the longest
    poll is the worst latency the server adds, and the queue depth at its start how far it
    fell behind. Percentiles are over the last `window` polls (bounded memory); worst, means
    and totals over all.
    """

    def __init__(self, window: int = 65536) -> None:
        self._seconds: deque[float] = deque(maxlen=window)
        self.polls = self.handled = self.max_depth = 0
        self.worst_s = self.total_s = 0.0
        self._depth_sum = 0

    def add(self, seconds: float, depth: int, handled: int) -> None:
        self._seconds.append(float(seconds))
        self.polls += 1
        self.handled += int(handled)
        self.total_s += float(seconds)
        self.worst_s = max(self.worst_s, float(seconds))
        self.max_depth = max(self.max_depth, int(depth))
        self._depth_sum += int(depth)

    def summary(self) -> dict[str, float | int]:
        """``polls``, ``messages``, ``busy_s`` (time in polls), ``worst_s``, ``p50_s``,
        ``p99_s``, ``max_queue_depth``, ``mean_queue_depth`` (0s before the first poll)."""
        times = np.asarray(self._seconds) if self._seconds else np.zeros(1)
        return {"polls": self.polls, "messages": self.handled, "busy_s": self.total_s,
                "worst_s": self.worst_s, "p50_s": float(np.percentile(times, 50)),
                "p99_s": float(np.percentile(times, 99)), "max_queue_depth": self.max_depth,
                "mean_queue_depth": self._depth_sum / max(self.polls, 1)}


def bus_metrics(session: str, traffic: Mapping[str, Table], seconds: float, received: Table,
                dropped: Mapping[str, int],
                sensor_s: Mapping[str, float | None] | None = None) -> dict:
    """The ``bus`` section of ``metrics.json``: `traffic` (`Bus.stats()`), `received`
    (`KeyCounter.table` of the agents' messages), `dropped` (key -> count), and the traffic per
    agent and per group over `seconds` of uptime (`sensor_s`: see `traffic_per_agent`)."""
    # The bus counts the agents' messages under the subscribed wildcard; per agent they come
    # from the node's own counts under each concrete key.
    by_key = {"sent": traffic["sent"], "received": {**traffic["received"], **received}}
    return {"dropped": dict(dropped), "traffic": traffic, "received_by_key": received,
            "per_agent": traffic_per_agent(session, by_key, seconds, sensor_s),
            "per_group": traffic_per_group(session, traffic["sent"], seconds)}


def traffic_per_agent(session: str, traffic: Mapping[str, Mapping], seconds: float,
                      sensor_s: Mapping[str, float | None] | None = None) -> dict[str, dict]:
    """Per agent: ``from_agent`` and ``to_agent`` tables of messages, bytes and bytes/s per
    topic, their totals ``<direction>_bytes`` and ``<direction>_bytes_per_s``.

    `traffic` is ``{"sent"|"received": {key: {"messages", "bytes"}}}``; keys are attributed with
    `keys.key_subject` (wildcard expressions and keys of no agent are skipped). Keyframe images
    count both ways under topic ``image`` (the request to the agent, the reply from it).
    A group's decoder reaches each member on its own key (topic ``group_decoder``). Rates
    are over `seconds` (the server's uptime); with `sensor_s` (agent -> sensor seconds of
    the frames it sent) every cell and total also gets ``bytes_per_sensor_s`` and the entry
    ``sensor_s``.
    """
    out: dict[str, dict] = {}

    def add(agent: str, direction: str, topic: str, row: Mapping) -> None:
        entry = out.setdefault(agent, {"from_agent": {}, "to_agent": {}})
        cell = entry[direction].setdefault(topic, {"messages": 0, "bytes": 0})
        cell["messages"] += int(row.get("messages", 0))
        cell["bytes"] += int(row.get("bytes", 0))

    for direction, table in (("from_agent", traffic.get("received", {})),
                             ("to_agent", traffic.get("sent", {}))):
        for key, row in table.items():
            subject = keys.key_subject(session, key)
            if subject is not None and subject[0] == "agent":
                add(subject[1], direction, subject[2], row)
    per_s = 1.0 / max(seconds, 1e-9)
    for agent, entry in out.items():
        sensor = (sensor_s or {}).get(agent)
        if sensor:
            entry["sensor_s"] = sensor
        for direction in ("from_agent", "to_agent"):
            for cell in entry[direction].values():
                cell["bytes_per_s"] = cell["bytes"] * per_s
                if sensor:
                    cell["bytes_per_sensor_s"] = cell["bytes"] / sensor
            total = sum(c["bytes"] for c in entry[direction].values())
            entry[f"{direction}_bytes"] = total
            entry[f"{direction}_bytes_per_s"] = total * per_s
            if sensor:
                entry[f"{direction}_bytes_per_sensor_s"] = total / sensor
    return out


def traffic_per_group(session: str, sent: Table, seconds: float) -> dict[str, dict]:
    """Per group: messages, bytes and bytes/s the server published on its decoder key for
    observers (once per round; each member's copy is in `traffic_per_agent`)."""
    out: dict[str, dict] = {}
    for key, row in sent.items():
        subject = keys.key_subject(session, key)
        if subject is None or subject[0] != "group":
            continue
        cell = out.setdefault(subject[1], {"messages": 0, "bytes": 0})
        cell["messages"] += int(row.get("messages", 0))
        cell["bytes"] += int(row.get("bytes", 0))
    for cell in out.values():
        cell["bytes_per_s"] = cell["bytes"] / max(seconds, 1e-9)
    return out
