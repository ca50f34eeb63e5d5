"""Loop verification on the back end's worker thread (`verify_in_background`, the daemon's
mode): a step never waits for a registration, messages are taken and acknowledged while one
runs, a candidate in the worker's hands survives a state snapshot, finalisation verifies
everything left, and the verdicts are those of inline verification.

Uses the drifting single agent of test_backend_loops.py (real registration, real database).
"""

from __future__ import annotations

import threading

import numpy as np
from fake_clock import FakeClock
from test_backend_loops import backend, feed, messages, scenario  # noqa: F401 - the fixture

from cpslam.common.registration import Registration
from cpslam.protocol import Ack
from cpslam.server.loops.registration import coarse_register


class GatedRegister:
    """The real coarse registration, held at a gate: the test decides when it may finish."""

    def __init__(self, loop) -> None:
        self.register = coarse_register(loop, 0)
        self.entered, self.gate = threading.Event(), threading.Event()
        self.threads: list[str] = []

    def __call__(self, src, dst) -> Registration:
        self.threads.append(threading.current_thread().name)
        self.entered.set()
        assert self.gate.wait(30.0), "the test never opened the gate"
        return self.register(src, dst)


def test_step_does_not_wait_for_a_registration(scenario):  # noqa: F811
    clock = FakeClock(0.0)
    be = backend(scenario, clock, verify_in_background=True)
    gated = GatedRegister(be.loop_cfg)
    be.pipeline.register = gated
    try:
        feed(be, scenario, clock, until_kf=5)  # keyframe 5 finds keyframe 0
        assert gated.entered.wait(30.0)  # the worker holds the pair, blocked in registration
        # The loop goes on: more messages are taken and acknowledged, steps return.
        later = [m for m in messages(scenario) if getattr(m, "kf_id", -1) == 6]
        out = be.handle(later[0]) + be.step()
        assert any(isinstance(o.message, Ack) for o in out)
        assert not be.loops and be.status()["loops"]["pending"] >= 1
        # A snapshot taken now keeps the pair in the worker's hands as queued.
        queued = {(a, ka, b, kb) for a, ka, b, kb, *_ in be.state_dict()["queued"]}
        assert ("solo", 5, "solo", 0) in queued
        gated.gate.set()
        assert be.pipeline.worker.wait_idle(30.0)
        be.step()
        (record,) = [lp for lp in be.loops if (lp.kf_a, lp.kf_b) == (5, 0)]
        assert record.accepted
        assert gated.threads and set(gated.threads) == {"loop-verify"}
    finally:
        gated.gate.set()
        be.close()
    assert be.pipeline.worker is None


def verdicts(be) -> dict:
    return {(lp.kf_a, lp.kf_b): (lp.accepted, np.asarray(lp.T_a_b)) for lp in be.loops}


def test_background_verifies_what_inline_does_and_finalise_leaves_nothing(scenario):  # noqa: F811
    results = {}
    for background in (False, True):
        clock = FakeClock(0.0)
        be = backend(scenario, clock, verify_in_background=background)
        for msg in messages(scenario):
            be.handle(msg)
            if type(msg).__name__ == "FramePoses":
                clock.advance(1.0)
                be.step()  # with the worker most verdicts are still pending here
        result = be.finalise()
        assert not be.pipeline.pending() and be.pipeline.worker is None
        results[background] = (verdicts(be), result.agents[0].T_own_cam)
        be.close()
    (inline, traj_inline), (threaded, traj_threaded) = results[False], results[True]
    assert inline and set(threaded) == set(inline)
    for pair, (accepted, T) in inline.items():
        assert threaded[pair][0] == accepted
        np.testing.assert_allclose(threaded[pair][1], T, atol=1e-9)
    # The same loops give the same final pose graph, whatever order they were concluded in.
    np.testing.assert_allclose(traj_threaded[:, :3, 3], traj_inline[:, :3, 3], atol=1e-4)
