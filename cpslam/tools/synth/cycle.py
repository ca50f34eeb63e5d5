"""The cycle of synthetic scenes that benches and `cpslam prior` draw from: room loops and
apartment walks in turn, every other pair with depth noise, one scene seed each."""

from __future__ import annotations

__all__ = ["scene_cycle"]


def scene_cycle(n: int, base: int) -> list[dict]:
    """n scenes from scene seed `base` on: dicts with name, kind ("room" or "apartment"),
    seed, noise and loop (room loops close their loop), as `generate` takes them."""
    specs = []
    for i in range(n):
        kind = "room" if i % 2 == 0 else "apartment"
        noise = (i // 2) % 2 == 1
        seed = base + i
        specs.append({"name": f"{kind}-{seed}{'-noise' if noise else ''}", "kind": kind,
                      "seed": seed, "noise": noise, "loop": kind == "room"})
    return specs
