"""The `limits` section: caps on everything a remote peer can key or size, and the plausibility
bounds the server checks agents' messages against (docs/deployment.md, Limits)."""

from __future__ import annotations

from pydantic import PositiveFloat, PositiveInt, model_validator

from cpslam.common.config.base import Section

__all__ = ["LimitsConfig"]

# The status reply is one `Status` message; the protocol refuses one over 1 MiB.
STATUS_MESSAGE_KB = 1024


class LimitsConfig(Section):
    """Caps on state keyed or sized by peers, and plausibility bounds of agents' messages."""

    max_agents: PositiveInt = 64
    """Agent ids the server accepts in a session; messages of further ids are dropped."""
    max_counter_keys: PositiveInt = 1024
    """Distinct keys (or reasons) a drop or traffic counter keeps; the rest count as "other"."""
    max_pending_frames: PositiveInt = 100_000
    """Frame poses of one agent waiting for their keyframe; the oldest beyond it are dropped."""
    max_pending_points: PositiveInt = 1_000_000
    """Sub-map points of one agent waiting for their keyframe; the oldest beyond it are dropped."""
    max_keyframes_per_agent: PositiveInt = 20_000
    """Keyframes the server keeps of one agent (11 h at 30 Hz, one in 20); further ones dropped."""
    max_points_per_agent: PositiveInt = 5_000_000
    """Map points the server keeps of one agent; a sub-map delta beyond it is dropped whole."""
    max_seq_ahead: PositiveInt = 100_000
    """A message whose seq is this far beyond the agent's acknowledged one is dropped unacked."""
    max_removed_per_message: PositiveInt = 500_000
    """Removed point ids one sub-map delta may carry; a larger delta is refused whole."""
    max_tombstones: PositiveInt = 2_000_000
    """Removed point ids remembered per agent; beyond it the oldest removals are forgotten."""
    image_cache_mb: PositiveFloat = 256.0
    """Bytes of keyframe images the server's loop pipeline keeps (MiB; oldest evicted first)."""
    queue_mb: PositiveFloat = 256.0
    """Bytes one subscription queue may hold (MiB) besides transport.queue_size messages."""
    max_translation_m: PositiveFloat = 10_000.0
    """Largest |t| (m) of a pose an agent reports; a message with a larger one is dropped."""
    max_federated_samples: PositiveInt = 1_000_000_000
    """Largest sample count a decoder submission may claim (its federated averaging weight)."""
    descriptor_dim: PositiveInt | None = None
    """Keyframe descriptor length the server accepts; null = derived from place_recognition."""
    status_reply_kb: PositiveInt = 512
    """Budget of the status reply (KiB); the summary is trimmed to fit (at most 1024)."""
    zenoh_max_sessions: PositiveInt = 256
    """Zenoh sessions (agents, clients, routers) the server's session admits at once."""

    @model_validator(mode="after")
    def _check(self) -> LimitsConfig:
        if self.status_reply_kb > STATUS_MESSAGE_KB:
            raise ValueError(
                f"status_reply_kb ({self.status_reply_kb}) must be at most "
                f"{STATUS_MESSAGE_KB} (the protocol's cap on a status message)"
            )
        return self
