"""Key expressions as Zenoh writes them: `/`-separated chunks, `*` one chunk, `**` any chunks.

Both buses validate keys here so that a key the in-memory bus accepts is one Zenoh accepts too.
Zenoh's sub-chunk wildcard `$*` is deliberately not supported: cpslam keys never need it and
keeping the grammar small keeps the in-memory matcher obviously right.
"""

from __future__ import annotations

from functools import lru_cache

__all__ = ["validate_key_expr", "validate_key", "is_concrete", "intersects", "reply_key"]

_FORBIDDEN = set("#?$")


def validate_key_expr(key_expr: str, what: str = "key expression") -> str:
    """Return `key_expr` unchanged if it is a canonical key expression, else raise ValueError."""
    if not isinstance(key_expr, str):
        raise TypeError(f"{what} must be a str, got {type(key_expr).__name__}")
    if not key_expr:
        raise ValueError(f"{what} must not be empty")
    chunks = key_expr.split("/")
    for chunk in chunks:
        if not chunk:
            raise ValueError(f"{what} {key_expr!r} has an empty chunk (leading, trailing or '//')")
        bad = _FORBIDDEN.intersection(chunk)
        if bad:
            raise ValueError(
                f"{what} {key_expr!r} contains forbidden character(s) {''.join(sorted(bad))!r}"
            )
        if "*" in chunk and chunk not in ("*", "**"):
            raise ValueError(f"{what} {key_expr!r}: '*' must form a whole chunk ('*' or '**')")
    for left, right in zip(chunks, chunks[1:], strict=False):
        if left == "**" and right in ("*", "**"):
            canonical = "*/**" if right == "*" else "**"
            raise ValueError(
                f"{what} {key_expr!r} is not canonical: write '**/{right}' as {canonical!r}"
            )
    return key_expr


def validate_key(key: str, what: str = "key") -> str:
    """Like `validate_key_expr` but also rejects wildcards (publications need a concrete key)."""
    validate_key_expr(key, what)
    if not is_concrete(key):
        raise ValueError(f"{what} {key!r} must be concrete (no '*' or '**')")
    return key


def is_concrete(key_expr: str) -> bool:
    """True when the key expression names exactly one key (no wildcard chunk)."""
    return "*" not in key_expr


def intersects(a: str, b: str) -> bool:
    """True when some concrete key matches both key expressions (Zenoh's `intersects`)."""
    return _intersects(tuple(a.split("/")), tuple(b.split("/")))


@lru_cache(maxsize=4096)
def _intersects(a: tuple[str, ...], b: tuple[str, ...]) -> bool:
    if not a or not b:
        rest = a or b
        return all(chunk == "**" for chunk in rest)
    if a[0] == "**":
        # `**` matches zero chunks (drop it) or swallows b's first chunk (keep it).
        return _intersects(a[1:], b) or _intersects(a, b[1:])
    if b[0] == "**":
        return _intersects(a, b[1:]) or _intersects(a[1:], b)
    if a[0] == "*" or b[0] == "*" or a[0] == b[0]:
        return _intersects(a[1:], b[1:])
    return False


def reply_key(query_key_expr: str, queryable_key_expr: str) -> str:
    """The key a queryable replies on: the most specific of the two that is concrete.

    Zenoh only accepts replies whose key intersects the query, and both arguments do.
    """
    if is_concrete(query_key_expr):
        return query_key_expr
    if is_concrete(queryable_key_expr):
        return queryable_key_expr
    return query_key_expr
