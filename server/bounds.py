"""The status summary trimmed to its byte budget, so ``cpslam status`` always gets an answer.

The summary lists agents, groups, drop counters and recent loops; each grows with what peers
send. `fit_status` keeps the summary whole when it fits and otherwise keeps at most n entries
of every table and list (the agents with most messages, the largest counters, the newest
loops), halving n until the encoded reply fits, and says so under ``"truncated"``.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import msgpack

from cpslam.protocol.base import PROTOCOL_VERSION

__all__ = ["fit_status", "status_size"]

# Tables of the summary whose rows are ranked by one number (the biggest are kept).
_RANK = {"agents": "messages"}


def status_size(summary: dict[str, Any]) -> int:
    """Encoded bytes of a `Status` reply carrying `summary` before compression (what the
    receiver's size cap applies to; no cap applied here)."""
    return len(
        msgpack.packb(
            {"type": "status", "version": PROTOCOL_VERSION, "stamp": 0.0, "summary": summary},
            use_bin_type=True,
        )
    )


def fit_status(
    summary: dict[str, Any], size: Callable[[dict[str, Any]], int], budget: int
) -> dict[str, Any]:
    """`summary`, or a trimmed copy whose `size` (encoded bytes) is at most `budget`.

    A trimmed copy has ``"truncated": {"entries_per_table", "budget_bytes", "omitted":
    {path: rows cut}}``; a cut counter keeps the cut counts under ``"other"``.
    """
    if size(summary) <= budget:
        return summary
    n = max(_longest(summary), 1)
    while n > 0:
        n //= 2
        omitted: dict[str, int] = {}
        trimmed = _trim(copy.deepcopy(summary), n, "", omitted)
        trimmed["truncated"] = {
            "entries_per_table": n,
            "budget_bytes": budget,
            "omitted": _top(omitted, n),
        }
        if size(trimmed) <= budget:
            return trimmed
    # Not even empty tables fit (huge scalars): only numbers are left.
    return {k: v for k, v in summary.items() if isinstance(v, int | float)} | {
        "truncated": {"entries_per_table": 0, "budget_bytes": budget, "omitted": {}}
    }


def _longest(node: Any) -> int:
    if isinstance(node, dict):
        return max([len(node), *(_longest(v) for v in node.values())])
    if isinstance(node, list):
        return max([len(node), *(_longest(v) for v in node)])
    return 0


def _trim(node: Any, n: int, path: str, omitted: dict[str, int]) -> Any:
    """Every dict and list below `node` cut to `n` entries (what was cut goes to
    `omitted` by path, or under "other" in a counter)."""
    if isinstance(node, dict):
        if len(node) > n:
            node = _keep(node, n, path, omitted)
        return {k: _trim(v, n, f"{path}/{k}", omitted) for k, v in node.items()}
    if isinstance(node, list):
        if len(node) > n:
            omitted[path] = len(node) - n
        # Lists are in arrival order: the newest are at the end.
        kept = node[len(node) - n :] if n else []
        return [_trim(v, n, path, omitted) for v in kept]
    return node


def _keep(table: dict, n: int, path: str, omitted: dict[str, int]) -> dict:
    by = _RANK.get(path.rsplit("/", 1)[-1], "")

    def rank(item: tuple[str, Any]) -> float:
        value = item[1]
        if isinstance(value, int | float):
            return float(value)
        if isinstance(value, dict) and isinstance(value.get(by), int | float):
            return float(value[by])
        return 0.0

    rows = sorted(table.items(), key=rank, reverse=True)
    if rows and all(isinstance(v, int) for _, v in rows):
        # A counter: what was cut still counts, under "other" (one of the n entries).
        keep = max(n - 1, 0)
        kept = dict(rows[:keep])
        rest = sum(v for _, v in rows[keep:])
        if n:
            kept["other"] = kept.get("other", 0) + rest
        omitted[path] = len(rows) - keep
        return kept
    omitted[path] = len(rows) - n
    return dict(rows[:n])


def _top(omitted: dict[str, int], n: int) -> dict[str, int]:
    """The `n` paths with the most rows cut (per-agent paths repeat per agent)."""
    return dict(sorted(omitted.items(), key=lambda kv: -kv[1])[: max(n, 1)])
