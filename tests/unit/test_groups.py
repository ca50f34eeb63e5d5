"""Groups: singleton start, merge composes the alignments, epochs, state round trip."""

from __future__ import annotations

import numpy as np
import pytest

from cpslam.common.geometry import compose, invert, se3_exp
from cpslam.server.groups import Groups


def pose(*xi):
    return se3_exp(np.asarray(xi, np.float64))


def test_each_agent_starts_alone_under_its_own_id():
    groups = Groups()
    g = groups.add_agent("a")
    assert g.group_id == "a" and g.members == ["a"] and g.agent_epoch == {"a": 0}
    assert groups.add_agent("a") is g
    np.testing.assert_array_equal(g.T_group_agent["a"], np.eye(4))


def test_merge_composes_both_groups_alignments():
    groups = Groups()
    for a in "abcd":
        groups.add_agent(a)
    # True worlds of the agents in one common frame W.
    W = {"a": pose(0, 0, 0, 0, 0, 0), "b": pose(1, 2, 0, 0, 0, 0.5),
         "c": pose(-1, 0, 1, 0.1, 0, 0), "d": pose(0, 3, 0, 0, 0.2, -0.4)}
    rel = lambda x, y: compose(invert(W[x]), W[y])  # noqa: E731 - world y in world x
    groups.merge("a", "b", rel("a", "b"))
    groups.merge("c", "d", rel("c", "d"))
    g = groups.merge("b", "d", rel("b", "d"))
    assert g.group_id == "a" and sorted(g.members) == list("abcd")
    for m in "abcd":
        np.testing.assert_allclose(g.T_group_agent[m], rel("a", m), atol=1e-9)
    assert g.agent_epoch == {"a": 0, "b": 1, "c": 1, "d": 2}
    assert list(groups.groups) == ["a"] and groups.same_group("a", "d")
    with pytest.raises(ValueError, match="already in group"):
        groups.merge("a", "c", np.eye(4))


def test_state_round_trip():
    groups = Groups()
    groups.add_agent("a")
    groups.add_agent("b")
    g = groups.merge("a", "b", pose(1, 0, 0, 0, 0, 1))
    g.decoder = {"w": np.ones(3, np.float32)}
    other = Groups()
    other.load_state_dict(groups.state_dict())
    h = other.group_of("b")
    assert h.members == g.members and h.epoch == g.epoch
    np.testing.assert_array_equal(h.T_group_agent["b"], g.T_group_agent["b"])
    np.testing.assert_array_equal(h.decoder["w"], g.decoder["w"])
