"""Federated averaging: fedavg for N agents, error messages, and round bookkeeping."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cpslam.server.federation import FederatedRound, fedavg, spread_pick


def make_states(n: int, seed: int = 0) -> list[dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    return [
        {
            "c.weight": rng.normal(size=(4, 3)).astype(np.float32),
            "c.bias": rng.normal(size=4).astype(np.float32),
        }
        for _ in range(n)
    ]


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5])
def test_fedavg_numpy_equals_hand_computed_average(n):
    states = make_states(n, seed=n)
    weights = [float(i + 1) ** 2 for i in range(n)]  # 1, 4, 9, ...
    out = fedavg(states, weights)
    assert list(out) == ["c.weight", "c.bias"]
    for key in out:
        expected = sum(w * s[key].astype(np.float64) for w, s in zip(weights, states, strict=True))
        expected /= sum(weights)
        assert isinstance(out[key], np.ndarray) and out[key].dtype == np.float32
        np.testing.assert_allclose(out[key], expected, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("n", [1, 3, 5])
def test_fedavg_torch_in_torch_out(n):
    states = [{k: torch.from_numpy(v) for k, v in s.items()} for s in make_states(n, seed=10)]
    weights = [0.0] + [1.0] * (n - 1) if n > 1 else [2.0]
    out = fedavg(states, weights)
    for key, value in out.items():
        assert isinstance(value, torch.Tensor) and value.dtype == torch.float32
        used = states[1:] if n > 1 else states
        expected = torch.stack([s[key].double() for s in used]).mean(0)
        torch.testing.assert_close(value.double(), expected, rtol=1e-6, atol=1e-7)


def test_fedavg_of_parameters_with_grad_does_not_track_history():
    layer = torch.nn.Linear(3, 2)
    out = fedavg([dict(layer.named_parameters())] * 2, [1.0, 1.0])
    assert not out["weight"].requires_grad
    torch.testing.assert_close(out["weight"], layer.weight.detach())


def test_fedavg_names_the_mismatching_key_and_agent():
    states = make_states(3)
    states[2]["c.bias"] = np.zeros(5, np.float32)
    with pytest.raises(ValueError, match=r"'c.bias' of agent #2 has shape \(5,\)"):
        fedavg(states, [1, 1, 1])
    states = make_states(3)
    del states[1]["c.weight"]
    with pytest.raises(ValueError, match=r"agent #1 lacks key 'c.weight'"):
        fedavg(states, [1, 1, 1])
    states = make_states(2)
    states[1]["extra"] = np.zeros(1, np.float32)
    with pytest.raises(ValueError, match=r"agent #1 has key 'extra'"):
        fedavg(states, [1, 1])
    states = make_states(2)
    states[1]["c.bias"] = torch.from_numpy(states[1]["c.bias"])
    with pytest.raises(ValueError, match=r"'c.bias' of agent #1 is Tensor"):
        fedavg(states, [1, 1])


@pytest.mark.parametrize(
    "weights, match",
    [([0, 0], "all zero"), ([1, -1], ">= 0"), ([1, float("nan")], "finite"), ([1], "1 weights")],
)
def test_fedavg_refuses_bad_weights(weights, match):
    with pytest.raises(ValueError, match=match):
        fedavg(make_states(2), weights)


def test_fedavg_refuses_no_states():
    with pytest.raises(ValueError, match="no states"):
        fedavg([], [])


def test_round_completes_when_all_members_submitted():
    states = make_states(3)
    rnd = FederatedRound("g0", 1, {"a", "b", "c"}, deadline_s=100.0)
    rnd.submit("a", states[0], n_samples=100)
    rnd.submit("b", states[1], n_samples=300)
    assert not rnd.is_complete(now=0.0)
    assert rnd.pending == {"c"}
    rnd.submit("c", states[2], n_samples=0)
    assert rnd.is_complete(now=0.0)
    averaged, contributors = rnd.result()
    assert contributors == ["a", "b", "c"]
    expected = fedavg(states, [100, 300, 0])
    np.testing.assert_allclose(averaged["c.weight"], expected["c.weight"])
    np.testing.assert_allclose(
        averaged["c.weight"],
        0.25 * states[0]["c.weight"] + 0.75 * states[1]["c.weight"],
        rtol=1e-5,
        atol=1e-6,
    )


def test_round_completes_on_deadline_with_one_submission():
    rnd = FederatedRound("g0", 2, ["a", "b"], deadline_s=10.0)
    assert not rnd.is_complete(now=11.0) and rnd.expired(now=11.0)
    rnd.submit("b", make_states(1)[0], n_samples=5)
    assert not rnd.is_complete(now=9.9)
    assert rnd.is_complete(now=10.0) and not rnd.expired(now=10.0)
    _, contributors = rnd.result()
    assert contributors == ["b"]


def test_dropped_member_never_blocks_the_round():
    states = make_states(3)
    rnd = FederatedRound("g1", 0, {"a", "b", "c"}, deadline_s=1e9)
    rnd.submit("a", states[0], n_samples=1)
    rnd.submit("b", states[1], n_samples=1)
    rnd.drop("c")
    assert rnd.is_complete(now=0.0)
    rnd.drop("b")  # left after submitting: its state is discarded
    averaged, contributors = rnd.result()
    assert contributors == ["a"]
    np.testing.assert_allclose(averaged["c.bias"], states[0]["c.bias"])


def test_round_uniform_weighting_and_all_zero_samples():
    states = make_states(2)
    for weighting, samples in [("uniform", (1, 9)), ("samples", (0, 0))]:
        rnd = FederatedRound("g", 0, {"a", "b"}, deadline_s=0.0, weighting=weighting)
        rnd.submit("a", states[0], n_samples=samples[0])
        rnd.submit("b", states[1], n_samples=samples[1])
        averaged, _ = rnd.result()
        np.testing.assert_allclose(
            averaged["c.bias"], (states[0]["c.bias"] + states[1]["c.bias"]) / 2, rtol=1e-6
        )


def test_round_refuses_strangers_and_empty_results():
    rnd = FederatedRound("g", 0, {"a"}, deadline_s=0.0)
    with pytest.raises(ValueError, match="'z' is not a member"):
        rnd.submit("z", make_states(1)[0], n_samples=1)
    with pytest.raises(ValueError, match="n_samples"):
        rnd.submit("a", make_states(1)[0], n_samples=-1)
    with pytest.raises(RuntimeError, match="no submissions"):
        rnd.result()
    with pytest.raises(ValueError, match="no members"):
        FederatedRound("g", 0, set(), deadline_s=0.0)


@pytest.mark.parametrize(("views", "pulled"), [(3, [0, 4, 9]), (None, list(range(10)))])
def test_finetune_views_spread_over_the_keyframes_or_all(views, pulled):
    """federation.finetune_views images, evenly spread; null (the paper) pulls every one."""
    from types import SimpleNamespace

    from spec_helpers import finetune_args, spec

    from cpslam.common.config.collab import FederationConfig
    from cpslam.server.federation import Federator
    from cpslam.server.groups import Group

    asked: list[int] = []
    registry = SimpleNamespace(agents={"a": SimpleNamespace(kf_ids=list(range(10)))})
    fed = Federator(FederationConfig(finetune_views=views), registry, None,
                    lambda agent, kf: asked.append(kf), lambda agent: {}, lambda group: [],
                    lambda: 0.0, 0.0, spec(), decoders_factory=None,
                    **{k: v for k, v in finetune_args().items() if k != "finetune_lr_features"})
    assert fed._views(Group("a", "a", T_group_agent={"a": np.eye(4)})) == []  # no image
    assert asked == pulled


def test_fine_tune_views_prefer_images_the_server_holds():
    assert spread_pick(20, 5).tolist() == [0, 5, 10, 14, 19]
    held = np.zeros(20, bool)
    held[[1, 6, 7, 13, 18]] = True
    # Each pick moves to the nearest held image within half the spacing (2.4 here).
    assert spread_pick(20, 5, held).tolist() == [1, 6, 10, 13, 18]
    assert spread_pick(20, 5, np.zeros(20, bool)).tolist() == [0, 5, 10, 14, 19]
    assert spread_pick(3, 8).tolist() == [0, 1, 2]
