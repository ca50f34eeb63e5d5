"""Keyframe depth on the wire: bytes and times of the two lossless codecs, PNG and zstd-delta.

For frames of an RGB-D sequence (default: the shared 7-Scenes kitchen frames, every 10th),
resized as an agent's keyframe replies are (`common.camera.resize_depth`) to the processed
size and to half of it, and coded as an agent codes them (millimetres, or inverse depth in
steps of k mm x depth²): the mean encoded size and the mean encode and decode time per image
of each codec, and the size ratio zstd-delta / PNG. Every image is checked to round-trip
exactly.

Usage: python bench/depth_codec.py [--data DIR] [--frames 0:300:10] [--scales 0.5 0.25]
           [--steps 0 0.65 1.3] [--json bench/results/depth-codec.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchinfo import bench_header  # noqa: E402

from cpslam.common.camera import resize_depth, scaled_size
from cpslam.common.datasets import open_sequence
from cpslam.protocol.image_messages import KeyframeImage
from cpslam.protocol.images import DEPTH_CODECS, depth_coding, image_from_wire, image_to_wire

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "7scenes-kitchen-0-299"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=SHARED, help="an RGB-D sequence")
    parser.add_argument("--frames", default="0:300:10", help="frames to code (start:stop:step)")
    parser.add_argument("--scales", type=float, nargs="+", default=[0.5, 0.25],
                        help="image sizes as fractions of the sequence's (0.5: the cpu preset)")
    parser.add_argument("--steps", type=float, nargs="+", default=[0.0, 0.65, 1.3],
                        help="depth steps k (mm x depth²); 0: millimetres")
    parser.add_argument("--json", type=Path, help="also write the report here")
    args = parser.parse_args()
    seq = open_sequence(args.data, frames=args.frames)
    depths = [frame.depth for frame in seq]
    rows = [measure(depths, scale, step) for scale in args.scales for step in args.steps]
    report = {**bench_header("depth_codec", sys.argv), "data": args.data.name,
              "frames": args.frames, "images": len(depths), "rows": rows}
    text = json.dumps(report, indent=2)
    if args.json is not None:
        args.json.write_text(text + "\n")
    print(text)


def measure(depths: list[np.ndarray], scale: float, step: float) -> dict:
    """Mean bytes and milliseconds per image of each codec at one size and step."""
    depth_scale, encoding = depth_coding(step)
    out: dict = {"scale": scale, "step_mm_per_m2": step}
    for codec in DEPTH_CODECS:
        sizes, enc_ms, dec_ms = [], [], []
        for depth_m in depths:
            height, width = depth_m.shape
            resized = resize_depth(depth_m, scaled_size(width, height, scale))
            coded = KeyframeImage.from_metres(
                resized, depth_scale, encoding, agent_id="a", kf_id=0, fx=1.0, fy=1.0,
                cx=0.0, cy=0.0, width=resized.shape[1], height=resized.shape[0]).depth
            t0 = time.perf_counter()
            wire = image_to_wire(coded, "depth", codec)
            t1 = time.perf_counter()
            back = image_from_wire(wire, "depth", coded.shape[1], coded.shape[0])
            t2 = time.perf_counter()
            if not np.array_equal(back, coded):
                raise AssertionError(f"{codec} did not round-trip")
            sizes.append(len(wire["data"]))
            enc_ms.append(1e3 * (t1 - t0))
            dec_ms.append(1e3 * (t2 - t1))
        out["size"] = list(coded.shape[::-1])
        out[codec] = {"bytes": round(float(np.mean(sizes))),
                      "encode_ms": round(float(np.mean(enc_ms)), 2),
                      "decode_ms": round(float(np.mean(dec_ms)), 2)}
    out["ratio"] = round(out["zstd-delta"]["bytes"] / out["png"]["bytes"], 3)
    return out


if __name__ == "__main__":
    main()
