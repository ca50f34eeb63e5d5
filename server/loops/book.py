"""The book of verified loop pairs.

`LoopBook` remembers which pairs were verified or rejected so that the same pair is not
verified again with every new keyframe, offers again a pair whose verification could not run
(a keyframe image was not available), up to a number of tries, and counts what was found,
accepted and rejected. The loop pipeline keeps its bookkeeping in one.
"""

from __future__ import annotations

from typing import Any

from cpslam.server.loops.candidates import Keyframe

__all__ = ["LoopBook"]

_STATE_VERSION = 1


class LoopBook:
    """Pairs of keyframes already verified (or being verified), and loop counts.

    A verdict (accepted or rejected) is final: the same images give the same verdict. A
    verification that could not run (``record(..., retry=True)``: a keyframe image was not
    available) leaves the pair to be offered again, until it has been tried ``max_attempts``
    times; the last such failure rejects it.

    Candidates are anything with ``agent_a, kf_a, agent_b, kf_b`` (`LoopCandidate`); a pair is
    the same whichever keyframe was the query.

    Args:
        max_attempts: tries of a pair whose verification could not run (1: never again).
    """

    def __init__(self, max_attempts: int = 1) -> None:
        if max_attempts < 1:
            raise ValueError(f"max_attempts must be >= 1, got {max_attempts}")
        self.max_attempts = int(max_attempts)
        self._status: dict[tuple[Keyframe, Keyframe], str] = {}
        self._attempts: dict[tuple[Keyframe, Keyframe], int] = {}
        self.found = 0
        """Distinct pairs offered for verification."""
        self.accepted = 0
        """Verifications that accepted a loop."""
        self.rejected = 0
        """Pairs rejected: by verification, or after ``max_attempts`` tries that could not run."""

    def select(self, candidates: list[Any]) -> list[Any]:
        """The candidates worth verifying now; they are marked pending until `record`.

        A pair is skipped while pending and once decided (accepted or rejected); a pair whose
        verification could not run is offered again. The same pair appearing twice in
        ``candidates`` is returned once.
        """
        out = []
        for cand in candidates:
            key = _pair_key(cand)
            status = self._status.get(key)
            if status in ("pending", "accepted", "rejected"):
                continue
            if status is None:
                self.found += 1
            self._status[key] = "pending"
            out.append(cand)
        return out

    def record(self, candidate: Any, accepted: bool, retry: bool = False) -> None:
        """Store the outcome of verifying a candidate returned by `select`.

        ``retry``: the verification could not run (``accepted`` is then ignored); the pair is
        offered again unless this was its ``max_attempts``-th try, which rejects it.
        """
        key = _pair_key(candidate)
        if self._status.get(key) != "pending":
            raise ValueError(f"record: pair {key} was not selected for verification")
        self._attempts[key] = self._attempts.get(key, 0) + 1
        if retry and self._attempts[key] < self.max_attempts:
            self._status[key] = "failed"
        elif accepted and not retry:
            self._status[key] = "accepted"
            self.accepted += 1
        else:
            self._status[key] = "rejected"
            self.rejected += 1

    def release(self, candidate: Any) -> None:
        """Give up a pending candidate without a verdict or a try (e.g. the step ran out of
        time before verifying it): it may be selected again."""
        key = _pair_key(candidate)
        if self._status.get(key) == "pending":
            if key in self._attempts:
                self._status[key] = "failed"
            else:
                del self._status[key]
                self.found -= 1

    def status(self, candidate: Any) -> str | None:
        """"pending", "accepted", "rejected", "failed" (could not be verified, will be offered
        again), or None for a pair never selected."""
        return self._status.get(_pair_key(candidate))

    def attempts(self, candidate: Any) -> int:
        """How many times the pair was recorded."""
        return self._attempts.get(_pair_key(candidate), 0)

    def accepted_pairs(self) -> list[tuple[Keyframe, Keyframe]]:
        """Pairs whose loop was accepted, in the order first selected."""
        return [k for k, s in self._status.items() if s == "accepted"]

    def metrics(self) -> dict[str, int]:
        """Counts for metrics.json."""
        pending = sum(1 for s in self._status.values() if s == "pending")
        retrying = sum(1 for s in self._status.values() if s == "failed")
        return {"found": self.found, "accepted": self.accepted, "rejected": self.rejected,
                "pending": pending, "retrying": retrying}

    def state_dict(self) -> dict[str, Any]:
        """Decided and retrying pairs and counts (pending pairs are not kept: nobody will
        record them)."""
        kept = [(k, s) for k, s in self._status.items() if s != "pending"]
        # A pair pending for the first time will be found again after a reload.
        first_pending = sum(1 for k, s in self._status.items()
                            if s == "pending" and k not in self._attempts)
        pending_tried = [(k, "failed") for k, s in self._status.items()
                         if s == "pending" and k in self._attempts]
        return {
            "version": _STATE_VERSION,
            "pairs": [[list(k[0]), list(k[1]), s, self._attempts[k]]
                      for k, s in kept + pending_tried],
            "found": self.found - first_pending,
            "accepted": self.accepted,
            "rejected": self.rejected,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Replace the contents with a `state_dict` (ValueError naming a bad entry)."""
        if state.get("version") != _STATE_VERSION:
            raise ValueError(
                f"loop book state: version {state.get('version')!r}, expected {_STATE_VERSION}"
            )
        status: dict[tuple[Keyframe, Keyframe], str] = {}
        attempts: dict[tuple[Keyframe, Keyframe], int] = {}
        for i, entry in enumerate(state.get("pairs", [])):
            try:
                (agent_a, kf_a), (agent_b, kf_b), verdict, n = entry
                key = ((str(agent_a), int(kf_a)), (str(agent_b), int(kf_b)))
            except (TypeError, ValueError):
                raise ValueError(
                    f"loop book state: pairs[{i}] must be [[agent, kf], [agent, kf], "
                    f"verdict, attempts], got {entry!r}"
                ) from None
            if verdict not in ("accepted", "rejected", "failed"):
                raise ValueError(f"loop book state: pairs[{i}] has verdict {verdict!r}")
            status[key], attempts[key] = verdict, int(n)
        self._status, self._attempts = status, attempts
        self.found = int(state.get("found", len(status)))
        self.accepted = int(state.get("accepted", 0))
        self.rejected = int(state.get("rejected", 0))


def _pair_key(cand: Any) -> tuple[Keyframe, Keyframe]:
    """The two keyframes of a candidate in a canonical order (as `LoopCandidate.pair`)."""
    a, b = (str(cand.agent_a), int(cand.kf_a)), (str(cand.agent_b), int(cand.kf_b))
    return (a, b) if a <= b else (b, a)
