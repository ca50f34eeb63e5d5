"""The other process of the loopback tests: a stand-in agent on a real Zenoh session.

    python tests/loopback/bus_peer.py --connect tcp/127.0.0.1:PORT [--mode client]

It declares, then prints READY and serves until stdin closes (or it is killed):
- liveliness token `keys.alive_agent(SESSION, AGENT)`, declared last (see below);
- round trip: every sample on `cpslam/<session>/test/roundtrip/<type>` is decoded with
  `cpslam.protocol.decode` (it must be a valid message of that type), re-encoded and published
  on `.../test/echo/<type>`; an invalid one is answered on `.../test/echo/invalid`;
- keyframe images: the image queryable `keys.agent_image_queryable(SESSION, AGENT)` decodes a
  `KeyframeImageRequest` payload and answers with a `KeyframeImage` of the requested keyframe;
- a deliberately slow subscriber on `.../test/flood` (FLOOD_SLEEP_S per sample, queue_size 4)
  and a queryable `.../test/stats` answering JSON {"handled": n, "stats": bus.stats()}.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
import time

from cpslam import protocol
from cpslam.common.bus import Sample, ZenohBus
from cpslam.protocol import keys
from cpslam.protocol.samples import sample

SESSION = "lb"
AGENT = "agent-0"
FLOOD_QUEUE_SIZE = 4
# Slow enough that a publisher waiting for this consumer could not pass the flood test.
FLOOD_SLEEP_S = 0.1


def lb_key(name: str) -> str:
    return f"cpslam/{SESSION}/test/{name}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--connect", action="append", default=[])
    parser.add_argument("--listen", action="append", default=[])
    parser.add_argument("--mode", default="client")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)

    bus = ZenohBus(mode=args.mode, listen=args.listen, connect=args.connect, lease_s=2.0)
    handled = 0
    handled_lock = threading.Lock()

    def roundtrip(s: Sample) -> None:
        msg_type = s.key.rsplit("/", 1)[-1]
        try:
            msg = protocol.decode(s.payload, expected=protocol.MESSAGE_TYPES[msg_type])
        except (protocol.ProtocolError, KeyError) as exc:
            bus.publish(lb_key("echo/invalid"), str(exc).encode())
            return
        bus.publish(lb_key(f"echo/{msg_type}"), protocol.encode(msg))

    def image(key: str, payload: bytes | None) -> bytes:
        _, kf_id = keys.parse_image_key(SESSION, key)
        request = protocol.decode(payload or b"", expected=protocol.KeyframeImageRequest)
        reply = sample("keyframe_image", width=64, height=48)
        return protocol.encode(
            reply.model_copy(update={"kf_id": kf_id, "agent_id": request.agent_id})
        )

    def slow(s: Sample) -> None:
        nonlocal handled
        time.sleep(FLOOD_SLEEP_S)
        with handled_lock:
            handled += 1

    def stats(key: str, payload: bytes | None) -> bytes:
        with handled_lock:
            return json.dumps({"handled": handled, "stats": bus.stats()}).encode()

    bus.subscribe(lb_key("roundtrip/*"), callback=roundtrip, queue_size=256)
    bus.declare_queryable(keys.agent_image_queryable(SESSION, AGENT), image)
    bus.subscribe(lb_key("flood"), callback=slow, queue_size=FLOOD_QUEUE_SIZE)
    bus.declare_queryable(lb_key("stats"), stats)
    # Last: declarations travel in order on the link, so a watcher that sees this token join
    # knows the subscriptions and queryables above have reached it too.
    bus.declare_liveliness(keys.alive_agent(SESSION, AGENT))
    print("READY", bus.zid, flush=True)
    sys.stdin.read()  # serve until the test closes our stdin
    bus.close()
    print("CLOSED", flush=True)


if __name__ == "__main__":
    main()
