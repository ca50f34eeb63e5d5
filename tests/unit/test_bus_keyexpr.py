"""Key-expression grammar and matching, checked against Zenoh's own implementation."""

from __future__ import annotations

import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from cpslam.common.bus.keyexpr import (
    intersects,
    is_concrete,
    reply_key,
    validate_key,
    validate_key_expr,
)

chunk = st.sampled_from(["a", "b", "ab", "*", "**"])
key_exprs = st.lists(chunk, min_size=1, max_size=5).map("/".join)


def zenoh_accepts(key_expr: str) -> bool:
    try:
        zenoh.KeyExpr(key_expr)
    except zenoh.ZError:
        return False
    return True


def ours_accepts(key_expr: str) -> bool:
    try:
        validate_key_expr(key_expr)
    except ValueError:
        return False
    return True


@settings(max_examples=300, deadline=None)
@given(key_exprs)
def test_validation_agrees_with_zenoh(key_expr: str) -> None:
    assert ours_accepts(key_expr) == zenoh_accepts(key_expr)


@settings(max_examples=500, deadline=None)
@given(key_exprs, key_exprs)
def test_intersection_agrees_with_zenoh(a: str, b: str) -> None:
    if not (ours_accepts(a) and ours_accepts(b)):
        return
    expected = zenoh.KeyExpr(a).intersects(zenoh.KeyExpr(b))
    assert intersects(a, b) == expected
    assert intersects(b, a) == expected


@pytest.mark.parametrize(
    ("a", "b", "expected"),
    [
        ("cpslam/s/agent/1/keyframe", "cpslam/s/agent/*/keyframe", True),
        ("cpslam/s/agent/1/keyframe", "cpslam/s/agent/*/submap", False),
        ("cpslam/s/agent/1/image/3", "cpslam/s/agent/1/image/*", True),
        ("cpslam/s/agent/1/image/3", "cpslam/**", True),
        ("cpslam", "cpslam/**", True),  # `**` also matches zero chunks
        ("cpslam/s", "cpslam/*/*", False),
        ("a/**/c", "a/b/b/c", True),
    ],
)
def test_intersects_examples(a: str, b: str, expected: bool) -> None:
    assert intersects(a, b) is expected


@pytest.mark.parametrize(
    ("bad", "message"),
    [
        ("", "empty"),
        ("a//b", "empty chunk"),
        ("a/b*", "whole chunk"),
        ("a/$*", "forbidden"),
        ("a/?", "forbidden"),
        ("a/**/**", "canonical"),
    ],
)
def test_validation_messages_name_the_problem(bad: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        validate_key_expr(bad)


def test_concrete_keys_and_reply_keys() -> None:
    assert is_concrete("a/b") and not is_concrete("a/*")
    with pytest.raises(ValueError, match="concrete"):
        validate_key("a/**", "publish key")
    with pytest.raises(TypeError):
        validate_key_expr(3)  # type: ignore[arg-type]
    assert reply_key("img/3", "img/*") == "img/3"
    assert reply_key("agent/*/status", "agent/2/status") == "agent/2/status"
    assert reply_key("agent/*/status", "agent/**") == "agent/*/status"
