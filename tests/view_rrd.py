"""Reading an .rrd back with Rerun's own reader (`rerun.chunk.RrdReader`), for the view tests."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np


def read_rrd(path: Path) -> dict[str, list[dict[str, list]]]:
    """Entity path (without the leading /) -> its logged rows, each {column: value}, in the
    order they were logged."""
    from rerun.chunk import RrdReader

    rows: dict[str, list[tuple[bytes, dict]]] = defaultdict(list)
    for chunk in RrdReader(path).stream().to_chunks():
        table = chunk.to_record_batch().to_pydict()
        n = chunk.num_rows
        for i in range(n):
            row = {k: v[i] for k, v in table.items()}
            # Row ids are time-ordered TUIDs: their big-endian bytes sort in logging order.
            rows[chunk.entity_path.lstrip("/")].append((row["rerun.controls.RowId"], row))
    return {k: [r for _, r in sorted(v, key=lambda x: x[0])] for k, v in rows.items()}


def last(rows: list[dict], column: str):
    """The latest non-empty value of `column` among `rows`."""
    values = [r[column] for r in rows if r.get(column) is not None]
    assert values, f"no {column} logged"
    return values[-1]


def positions(rows: list[dict], column: str = "Points3D:positions") -> np.ndarray:
    return np.asarray(last(rows, column), dtype=np.float64).reshape(-1, 3)


def strips(rows: list[dict]) -> list[np.ndarray]:
    return [np.asarray(s, dtype=np.float64).reshape(-1, 3)
            for s in last(rows, "LineStrips3D:strips")]
