"""A wire recording: every message one agent sent the server, with its timing and images.

With ``link.record`` on, an `AgentNode` writes ``agent_<id>/wire.rec``: each message its link
produced (keyframes, sub-map deltas, decoder weights, frame poses; not resends, not update
acks), as the encoded bytes it published, with the seconds since the node started; at the
end the encoded `KeyframeImage` of every keyframe it kept, so a replay can answer the
server's image requests. The load harness (`cpslam.tools.replay`, ``bench/scale.py``)
replays such recordings as many agents.

File format: a stream of msgpack maps, first ``{"kind": "header", "format": "cpslam-wire",
"version": 1, "agent_id", "session", "incarnation"}``, then ``{"kind": "message", "t": s,
"stamp": s, "topic": "keyframe"|"submap"|"decoder"|"frames", "payload": bytes}`` in send
order (``t``: seconds since the node started; ``stamp``: sensor seconds of the frame that
produced the message since the first frame, what an agent keeping up with its camera would
publish by) and
``{"kind": "image", "kf_id": int, "payload": bytes}``. The writer stops recording (one
warning) at ``link.record_mb``; the reader refuses a record over `MAX_RECORD_BYTES` or a
file over its `max_mb`, naming the file and the record.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, NamedTuple

import msgpack

__all__ = [
    "FORMAT",
    "MAX_RECORD_BYTES",
    "TOPICS",
    "RecordedMessage",
    "Recording",
    "WireRecorder",
    "read_recording",
]

logger = logging.getLogger(__name__)

FORMAT = "cpslam-wire"
VERSION = 1
MB = 1 << 20
MAX_RECORD_BYTES = 80 * MB
"""Largest record a reader accepts (a sub-map delta may be 64 MiB, plus the record's keys)."""
TOPICS = ("keyframe", "submap", "decoder", "frames")
"""Topics (the last part of ``agent/<id>/<topic>``) a recording holds."""


class WireRecorder:
    """Appends one agent's outgoing messages and keyframe images to a recording file.

    Args:
        path: the file (its folder is created).
        agent_id, session, incarnation: written into the header.
        max_mb: recording stops (one warning) once the file would exceed this (MiB).
        start: the time origin of the records' ``t`` (s, the caller's clock).
    """

    def __init__(
        self,
        path: str | Path,
        agent_id: str,
        session: str,
        incarnation: int,
        max_mb: float = 1024.0,
        start: float = 0.0,
    ) -> None:
        if max_mb <= 0:
            raise ValueError(f"WireRecorder: max_mb must be > 0, got {max_mb}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.max_bytes = int(max_mb * MB)
        self.start = float(start)
        self.bytes = 0
        self.messages = 0
        self.images = 0
        self.full = False
        # private like the run's other outputs: it holds the agent's images
        fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        self._fh: BinaryIO | None = os.fdopen(fd, "wb")
        self._write(
            {
                "kind": "header",
                "format": FORMAT,
                "version": VERSION,
                "agent_id": agent_id,
                "session": session,
                "incarnation": int(incarnation),
            }
        )

    def message(self, t: float, topic: str, payload: bytes, stamp: float = 0.0) -> None:
        """One published message (`t` on the clock `start` is on; `stamp`: sensor seconds
        since the first frame)."""
        if topic not in TOPICS:
            raise ValueError(f"WireRecorder: topic {topic!r} is not one of {TOPICS}")
        if self._write(
            {
                "kind": "message",
                "t": max(float(t) - self.start, 0.0),
                "stamp": max(float(stamp), 0.0),
                "topic": topic,
                "payload": bytes(payload),
            }
        ):
            self.messages += 1

    def image(self, kf_id: int, payload: bytes) -> None:
        """A keyframe's encoded `KeyframeImage`."""
        if self._write({"kind": "image", "kf_id": int(kf_id), "payload": bytes(payload)}):
            self.images += 1

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None
            logger.info(
                "wire recording %s: %d messages, %d images, %.1f MiB",
                self.path,
                self.messages,
                self.images,
                self.bytes / MB,
            )

    def _write(self, record: dict[str, Any]) -> bool:
        if self._fh is None or self.full:
            return False
        data = msgpack.packb(record, use_bin_type=True)
        if self.bytes + len(data) > self.max_bytes:
            self.full = True
            logger.warning(
                "wire recording %s: reached link.record_mb (%.0f MiB); the rest of "
                "this run is not recorded",
                self.path,
                self.max_bytes / MB,
            )
            return False
        self._fh.write(data)
        self.bytes += len(data)
        return True


class RecordedMessage(NamedTuple):
    t: float
    """Seconds since the agent started."""
    topic: str
    payload: bytes
    """The encoded message as published."""
    stamp: float
    """Sensor seconds of the frame that produced it, since the first frame."""


@dataclass
class Recording:
    """A recording read back: header fields, messages in send order, images by keyframe."""

    path: Path
    agent_id: str
    session: str
    incarnation: int
    messages: list[RecordedMessage] = field(default_factory=list)
    """In send order."""
    images: dict[int, bytes] = field(default_factory=dict)
    """kf_id -> encoded `KeyframeImage`."""

    @property
    def duration_s(self) -> float:
        """Seconds from the start to the last message."""
        return self.messages[-1].t if self.messages else 0.0

    @property
    def sensor_s(self) -> float:
        """Sensor seconds from the first frame to the last message."""
        return self.messages[-1].stamp if self.messages else 0.0


def read_recording(path: str | Path, max_mb: float = 4096.0) -> Recording:
    """Read a ``wire.rec``; raises ValueError naming the file and record when it is not one."""
    path = Path(path)
    size = path.stat().st_size
    if size > max_mb * MB:
        raise ValueError(
            f"{path}: {size / MB:.0f} MiB, more than the {max_mb:.0f} MiB a recording may have"
        )
    with path.open("rb") as fh:
        unpacker = msgpack.Unpacker(
            fh, raw=False, max_buffer_size=MAX_RECORD_BYTES, strict_map_key=True
        )
        rec: Recording | None = None
        try:
            for i, record in enumerate(unpacker):
                rec = _add(path, i, record, rec)
        except (msgpack.UnpackException, ValueError) as exc:
            if isinstance(exc, ValueError) and str(exc).startswith(str(path)):
                raise
            raise ValueError(f"{path}: not a readable wire recording ({exc})") from exc
    if rec is None:
        raise ValueError(f"{path}: empty; expected a {FORMAT} header record")
    return rec


def _add(path: Path, i: int, record: Any, rec: Recording | None) -> Recording:
    where = f"{path}: record {i}"
    if not isinstance(record, dict):
        raise ValueError(f"{where}: expected a map, got {type(record).__name__}")
    kind = record.get("kind")
    if rec is None:
        if kind != "header" or record.get("format") != FORMAT:
            raise ValueError(f"{where}: expected a {FORMAT} header first, got kind {kind!r}")
        if record.get("version") != VERSION:
            raise ValueError(
                f"{where}: version {record.get('version')!r}, this reader reads {VERSION}"
            )
        agent, session, inc = (record.get(k) for k in ("agent_id", "session", "incarnation"))
        if not (isinstance(agent, str) and isinstance(session, str) and isinstance(inc, int)):
            raise ValueError(f"{where}: header needs agent_id, session (str), incarnation (int)")
        return Recording(path, agent, session, inc)
    payload = record.get("payload")
    if not isinstance(payload, bytes):
        raise ValueError(f"{where}: payload must be bytes")
    if kind == "message":
        t, topic, stamp = record.get("t"), record.get("topic"), record.get("stamp")
        for name, value in (("t", t), ("stamp", stamp)):
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ValueError(f"{where}: {name} must be a finite number >= 0, got {value!r}")
        if topic not in TOPICS:
            raise ValueError(f"{where}: topic {topic!r} is not one of {TOPICS}")
        rec.messages.append(RecordedMessage(float(t), topic, payload, float(stamp)))
    elif kind == "image":
        kf = record.get("kf_id")
        if not isinstance(kf, int) or kf < 0:
            raise ValueError(f"{where}: kf_id must be an int >= 0, got {kf!r}")
        rec.images[kf] = payload
    else:
        raise ValueError(f"{where}: kind {kind!r}, expected message or image")
    return rec
