"""Where an agent's bytes go: per message type and per field of a wire recording.

Reads one or more wire recordings (``agent_<id>/wire.rec``, written with ``link.record=true``,
docs/scale.md) and prints, per topic, the messages and the bytes they took on the wire, then
per field of that topic's messages: its bytes in the msgpack map (an array's data, any other
value as msgpack) and those bytes compressed alone at the encoder's zstd level (or left as
they are where a zstd frame would be longer), with the
share of the topic's compressed fields. A field that zstd cannot shrink (int8 features,
JPEG) shows a ratio near 1; one that it can (sorted ids, positions in fixed point) far
below. Shares are of the fields compressed one by one, which a whole message compresses a
little better than.

Usage: python bench/wire_fields.py RUN/agent_0/wire.rec [RUN/agent_1/wire.rec ...]
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path
from typing import Any

import msgpack

from cpslam.agent.recording import read_recording
from cpslam.protocol.codec import DEFAULT_ZSTD_LEVEL, MAX_MESSAGE_BYTES
from cpslam.protocol.quant import compress, decompress, is_compressed

_HEADER = ("type", "version")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("recordings", nargs="+", type=Path, help="wire.rec files")
    parser.add_argument("--level", type=int, default=DEFAULT_ZSTD_LEVEL,
                        help="zstd level of the per-field compression")
    args = parser.parse_args()
    print_breakdown(field_bytes(args.recordings, args.level))


def field_bytes(paths: list[Path], level: int = DEFAULT_ZSTD_LEVEL) -> dict[str, dict]:
    """Per topic: {"messages", "wire", "fields": {name: {"raw", "zstd"}}} summed over the
    recordings' messages (images the recordings keep for replays are not messages)."""
    topics: dict[str, dict] = defaultdict(
        lambda: {"messages": 0, "wire": 0, "fields": defaultdict(lambda: {"raw": 0, "zstd": 0})}
    )
    for path in paths:
        for record in read_recording(path).messages:
            entry = topics[record.topic]
            entry["messages"] += 1
            entry["wire"] += len(record.payload)
            payload = record.payload
            if is_compressed(payload):
                payload = decompress(payload, MAX_MESSAGE_BYTES)
            for name, value in msgpack.unpackb(payload, raw=False).items():
                if name in _HEADER:
                    continue
                data = _field_data(value)
                entry["fields"][name]["raw"] += len(data)
                # as the encoder does: a frame that does not shrink the data is not used
                entry["fields"][name]["zstd"] += min(len(compress(data, level)), len(data))
    return {t: {**e, "fields": dict(e["fields"])} for t, e in sorted(topics.items())}


def _field_data(value: Any) -> bytes:
    """The bytes a field holds: an array's or image's data, or the value as msgpack."""
    if isinstance(value, dict) and "data" in value and isinstance(value["data"], bytes):
        return value["data"]
    return msgpack.packb(value, use_bin_type=True)


def print_breakdown(topics: dict[str, dict]) -> None:
    """One table per topic, fields by compressed size."""
    for topic, entry in topics.items():
        print(f"{topic}: {entry['messages']} messages, {entry['wire']} bytes on the wire")
        total = sum(f["zstd"] for f in entry["fields"].values()) or 1
        print(f"  {'field':24s} {'raw':>10s} {'zstd':>10s} {'ratio':>6s} {'share':>6s}")
        ranked = sorted(entry["fields"].items(), key=lambda kv: -kv[1]["zstd"])
        for name, f in ranked:
            ratio = f["zstd"] / f["raw"] if f["raw"] else 0.0
            print(f"  {name:24s} {f['raw']:10d} {f['zstd']:10d} {ratio:6.2f} "
                  f"{100 * f['zstd'] / total:5.1f}%")


if __name__ == "__main__":
    main()
