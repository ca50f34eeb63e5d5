"""Motion models: where the next frame probably is, from the trajectory so far."""

from __future__ import annotations

import itertools

import numpy as np

__all__ = ["MOTION_MODELS", "motion_guesses"]

MOTION_MODELS = ("zero_motion", "constant_velocity")


def motion_guesses(T_world_cam: list[np.ndarray], tracked: list[bool]) -> dict[str, np.ndarray]:
    """Initial poses [4, 4] of the next frame per motion model, from the last frames whose
    tracking was not lost (a lost frame's pose would mislead them).

    T_world_cam: every frame's pose so far (at least one); tracked: False where lost.
    "zero_motion" is the last good pose; "constant_velocity" (when the last two good frames
    are consecutive) repeats their relative motion once per frame since.
    """
    good = list(itertools.islice(
        (i for i in range(len(T_world_cam) - 1, -1, -1) if tracked[i]), 2))
    if not good:
        return {"zero_motion": T_world_cam[-1].copy()}
    previous = T_world_cam[good[0]]
    guesses = {"zero_motion": previous.copy()}
    if len(good) == 2 and good[0] - good[1] == 1:
        # T_k = T_{k-1} M, with M = T_{k-2}^-1 T_{k-1}.
        motion = np.linalg.inv(T_world_cam[good[1]]) @ previous
        guess = previous
        for _ in range(len(T_world_cam) - good[0]):
            guess = guess @ motion
        guesses["constant_velocity"] = guess
    return guesses
