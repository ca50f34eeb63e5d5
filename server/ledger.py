"""Which foreign points each agent holds, as far as its acknowledgements prove.

`ForeignTracker` keeps, per (receiver, source), the points the receiver surely holds and at
which version (``held``: confirmed by an `UpdateAck`) and the points it may hold in an unknown
state (``maybe``: touched by updates not acknowledged yet, or by updates whose fate is lost).
An update sends every needed point that is not surely held at its current version (so a lost
update is repaired by the next one) and removes every point possibly held that is no longer
needed. The receiver applies updates once each in increasing seq (skipping lost ones), so an
acknowledged update fixes the state of every point it touched unless a later update touched it
too. A large update is split into parts (each its own update seq) of at most ``max_points``
points; any part applied alone is consistent.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch

from cpslam.protocol import ForeignPoints

if TYPE_CHECKING:
    from cpslam.server.fusion import MemberMap

__all__ = ["ForeignTracker"]

Touched = dict[str, tuple[dict[int, int], set[int]]]  # source -> (sent id -> version, removed)


class ForeignTracker:
    """Foreign points per receiver: held (acknowledged), maybe (in flight or lost).

    Args:
        max_inflight: unacknowledged updates remembered per receiver; an older one is
            forgotten (its points stay in ``maybe`` and are sent or removed again).
    """

    def __init__(self, max_inflight: int = 64) -> None:
        self.max_inflight = int(max_inflight)
        self.held: dict[tuple[str, str], dict[int, int]] = {}
        """(receiver, source) -> point id -> version the receiver surely holds."""
        self.maybe: dict[tuple[str, str], set[int]] = {}
        """(receiver, source) -> point ids in an unknown state at the receiver."""
        self.inflight: dict[str, OrderedDict[int, Touched]] = {}
        """receiver -> update seq -> what it touched, oldest first."""

    def blocks(
        self,
        receiver: MemberMap,
        others: Sequence[MemberMap],
        versions: Mapping[str, np.ndarray],
        cell_size: float,
        seq: int,
    ) -> list[ForeignPoints]:
        """One update's `ForeignPoints` (unsplit; see `parts`)."""
        return self.parts(receiver, others, versions, cell_size, seq, max_points=None)[0]

    def parts(
        self,
        receiver: MemberMap,
        others: Sequence[MemberMap],
        versions: Mapping[str, np.ndarray],
        cell_size: float,
        first_seq: int,
        max_points: int | None,
    ) -> list[list[ForeignPoints]]:
        """The blocks of updates ``first_seq, first_seq + 1, …``: one `ForeignPoints` per
        other member in each (all its keyframe poses; removals in the first part only) and
        at most `max_points` points per part (None: one part)."""
        from cpslam.server.fusion import select_foreign

        masks = select_foreign(receiver, others, cell_size)
        r = receiver.agent_id
        chosen: list[tuple[MemberMap, np.ndarray, np.ndarray, np.ndarray]] = []
        for m in others:
            ids = m.point_map.point_id.cpu().numpy()
            version = np.asarray(versions[m.agent_id])
            key = (r, m.agent_id)
            held, maybe = self.held.setdefault(key, {}), self.maybe.setdefault(key, set())
            need = masks[m.agent_id]
            stale = np.array(
                [
                    held.get(int(i)) != int(v) or int(i) in maybe
                    for i, v in zip(ids, version, strict=True)
                ],
                dtype=bool,
            )
            send = np.nonzero(need & stale)[0]
            gone = np.asarray(sorted((set(held) | maybe) - set(ids[need].tolist())), np.int64)
            chosen.append((m, send, gone, version))
        total = sum(len(c[1]) for c in chosen)
        n_parts = 1 if not max_points else max(1, -(-total // int(max_points)))
        per = -(-total // n_parts) if total else 0
        out: list[list[ForeignPoints]] = [[] for _ in range(n_parts)]
        touched: list[Touched] = [{} for _ in range(n_parts)]
        offset = 0  # points placed in earlier blocks, over all sources
        for m, send, gone, version in chosen:
            pm = m.point_map
            ids = pm.point_id.cpu().numpy()
            cut = [min(max(p * per - offset, 0), len(send)) for p in range(n_parts)] + [len(send)]
            offset += len(send)
            for p in range(n_parts):
                rows = send[cut[p] : cut[p + 1]]
                removed = gone if p == 0 else np.zeros(0, np.int64)
                out[p].append(
                    ForeignPoints(
                        source_agent_id=m.agent_id,
                        kf_ids=pm.kf_keys[:, 1].cpu().numpy().astype(np.int32),
                        T_group_kf=pm.kf_poses.cpu().numpy(),
                        point_ids=ids[rows],
                        anchor_kf_ids=pm.anchor_kf.cpu().numpy()[rows].astype(np.int32),
                        xyz_local=pm.xyz_local.cpu().numpy()[rows],
                        features=pm.features.detach().cpu().numpy()[rows].astype(np.float16),
                        colors=pm.color.cpu().numpy()[rows],
                        removed_ids=removed,
                    )
                )
                touched[p][m.agent_id] = (
                    {int(i): int(v) for i, v in zip(ids[rows], version[rows], strict=True)},
                    set(removed.tolist()),
                )
        for p, entry in enumerate(touched):
            self._record(r, first_seq + p, entry)
        return out

    def _record(self, receiver: str, seq: int, entry: Touched) -> None:
        for source, (sent, removed) in entry.items():
            key = (receiver, source)
            held, maybe = self.held.setdefault(key, {}), self.maybe.setdefault(key, set())
            for i in (*sent, *removed):
                held.pop(i, None)
                maybe.add(i)
        flight = self.inflight.setdefault(receiver, OrderedDict())
        flight[seq] = entry
        while len(flight) > self.max_inflight:
            flight.popitem(last=False)  # its points stay in maybe: sent or removed again

    def acked(self, receiver: str, seq: int) -> bool:
        """The receiver applied update `seq`: what it touched (and no later update in flight
        touched) is now known. False when `seq` is not in flight (a repeat, or forgotten)."""
        flight = self.inflight.get(receiver, OrderedDict())
        if seq not in flight:
            return False
        later: dict[str, set[int]] = {}
        for s, entry in flight.items():
            if s > seq:
                for source, (sent, removed) in entry.items():
                    later.setdefault(source, set()).update(sent, removed)
        for source, (sent, removed) in flight[seq].items():
            key, skip = (receiver, source), later.get(source, set())
            held, maybe = self.held.setdefault(key, {}), self.maybe.setdefault(key, set())
            for i, v in sent.items():
                if i not in skip:
                    held[i] = v
                    maybe.discard(i)
            for i in removed - skip:
                maybe.discard(i)
        for s in [s for s in flight if s <= seq]:
            del flight[s]
        return True

    def pending(self, receiver: str) -> bool:
        """Updates in flight, or points in an unknown state, for this receiver."""
        return bool(self.inflight.get(receiver)) or any(
            v for (r, _), v in self.maybe.items() if r == receiver
        )

    def delivered(self, receiver: str) -> dict[str, dict[int, int]]:
        """Source -> point id -> version the receiver surely holds."""
        return {s: dict(d) for (r, s), d in self.held.items() if r == receiver and d}

    def forget(self, receiver: str) -> None:
        """Forget what `receiver` holds (it will get everything again)."""
        for table in (self.held, self.maybe):
            for key in [k for k in table if k[0] == receiver]:
                del table[key]
        self.inflight.pop(receiver, None)

    def state_dict(self) -> dict:
        """Held and maybe per (receiver, source); updates in flight are in maybe already."""
        held = {
            f"{r}\n{s}": torch.tensor(sorted(d.items()), dtype=torch.int64).reshape(-1, 2)
            for (r, s), d in self.held.items()
        }
        maybe = {
            f"{r}\n{s}": torch.tensor(sorted(v), dtype=torch.int64)
            for (r, s), v in self.maybe.items()
        }
        return {"held": held, "maybe": maybe}

    def load_state_dict(self, state: dict) -> None:
        """Restore a `state_dict` (an older flat one is read as ``held``)."""
        held, maybe = (state["held"], state["maybe"]) if "held" in state else (state, {})
        self.held = {
            tuple(k.split("\n")): {int(i): int(v) for i, v in t.tolist()}  # type: ignore[misc]
            for k, t in held.items()
        }
        self.maybe = {
            tuple(k.split("\n")): {int(i) for i in t.tolist()}  # type: ignore[misc]
            for k, t in maybe.items()
        }
        self.inflight = {}
