"""Sections of the running processes: the message bus and run-level settings."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Literal

from pydantic import (
    Field,
    NonNegativeFloat,
    NonNegativeInt,
    PositiveFloat,
    PositiveInt,
    field_validator,
    model_validator,
)

from cpslam.common.config.base import Section

__all__ = ["LinkConfig", "RunConfig", "TransportConfig"]


_ENDPOINT = re.compile(
    r"^(?:(?:tcp|udp|quic|tls|ws)/(?:\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):\d{1,5}"
    r"|unixsock-stream/\S+)(?:[?#]\S*)?$"
)


class TransportConfig(Section):
    """The message bus between agents and server (Eclipse Zenoh, or in-memory for tests)."""

    backend: Literal["zenoh", "memory"] = "zenoh"
    """Bus implementation: Zenoh, or the in-process bus (one process, tests and demos)."""
    session: str = "default"
    """Session name; every key expression lives under cpslam/{session}/."""
    mode: Literal["router", "peer", "client"] | None = None
    """Zenoh mode; null = the role's default (server: router, agent: client)."""
    listen: list[str] = []
    """Endpoints to listen on; empty = the role's default (server: tcp/0.0.0.0:7447)."""
    connect: list[str] = []
    """Endpoints to connect to; empty = the role's default (agent: tcp/127.0.0.1:7447)."""
    multicast_scouting: bool = False
    """Discover peers by UDP multicast (off: endpoints are explicit)."""
    shared_memory: bool = False
    """Let same-host Zenoh sessions exchange payloads through shared memory."""
    lease_s: PositiveFloat = 3.0
    """Zenoh lease (s): a silent peer is declared gone after this."""
    queue_size: PositiveInt = 64
    """Incoming messages buffered per subscription before the oldest are dropped."""
    max_message_mb: PositiveFloat = 64.0
    """Messages larger than this (MiB) are refused on send and dropped on receive."""
    open_timeout_s: PositiveFloat = 5.0
    """Time (s) allowed for opening a session and reaching the connect endpoints."""
    tls_root_ca: Path | None = None
    """CA certificate (PEM) that peers' TLS certificates must be signed by (tls/, quic/)."""
    tls_cert: Path | None = None
    """This process's TLS certificate (PEM), for listening and for mutual TLS when connecting."""
    tls_key: Path | None = None
    """Private key (PEM) of tls_cert."""
    tls_mtls: bool = False
    """Mutual TLS: a listener demands a client certificate, a client presents tls_cert."""
    tls_verify_name: bool = True
    """A client checks that the server's certificate names the host it connects to."""
    auth_user: str | None = None
    """User name for Zenoh's user-password authentication when connecting; null = none."""
    auth_password_file: Path | None = None
    """File whose first line is auth_user's password (kept out of the saved config)."""
    auth_dictionary: Path | None = None
    """Zenoh credentials file (user:password lines) a listener accepts; null = no check."""
    access_control: Path | None = None
    """JSON5 file with Zenoh's access_control object (rules, subjects, policies)."""
    zenoh_config: Path | None = None
    """Zenoh JSON5 config file applied first; the transport keys set here override it."""
    resend_after_s: PositiveFloat = 5.0
    """Time (s) after which an unacknowledged message or server update is sent again."""
    outbox_messages: PositiveInt = 4096
    """An agent stops taking frames while this many of its messages wait for an ack."""
    outbox_mb: PositiveFloat = 1024.0
    """An agent stops taking frames while its unacknowledged messages hold this much (MiB)."""
    update_window: PositiveInt = 1024
    """An agent ignores a server update more than this many seqs above its last applied one."""
    update_max_points: PositiveInt = 200_000
    """Most foreign points in one server update; a larger one is split into several."""

    @model_validator(mode="after")
    def _pairs(self) -> TransportConfig:
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("tls_cert and tls_key must be set together")
        if (self.auth_user is None) != (self.auth_password_file is None):
            raise ValueError("auth_user and auth_password_file must be set together")
        return self

    @field_validator("session")
    @classmethod
    def _session_name(cls, value: str) -> str:
        # Same rule as protocol ids: the session is a chunk of every key expression.
        if not re.fullmatch(r"[A-Za-z0-9_-]{1,64}", value):
            raise ValueError(
                f"session {value!r} must be 1-64 letters, digits, '_' or '-'"
            )
        return value

    @field_validator("listen", "connect", mode="before")
    @classmethod
    def _split_endpoints(cls, value: object) -> object:
        # Environment variables and --set give one string; accept "a,b" as a list.
        if isinstance(value, str):
            return [part.strip() for part in value.split(",") if part.strip()]
        return value

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, value: list[str]) -> list[str]:
        for endpoint in value:
            if not _ENDPOINT.match(endpoint):
                raise ValueError(
                    f"endpoint {endpoint!r} should look like tcp/HOST:PORT "
                    "(or udp/, quic/, tls/, ws/HOST:PORT, unixsock-stream/PATH)"
                )
            port = re.search(r":(\d+)(?:[?#]|$)", endpoint)
            if port and int(port.group(1)) > 65535:
                raise ValueError(f"endpoint {endpoint!r}: port must be at most 65535")
        return value


class LinkConfig(Section):
    """What an agent sends the server and how compactly (docs/protocol.md, wire-size budget)."""

    submap_every_mappings: PositiveInt = 4
    """Send a sub-map delta every this many mapping calls (the first call's at once)."""
    feature_threshold: NonNegativeFloat = 0.1
    """Resend a known point when a feature moved by this fraction of its largest (0: any)."""
    feature_rows: bool = True
    """Resend a point the server acknowledged as its features alone, without position or colour."""
    held_every_deltas: PositiveInt = 2
    """Points the server holds go again only with every this-many-th sub-map delta (new: each)."""
    feature_codec: Literal["float16", "int8"] = "int8"
    """Sub-map features on the wire: float16, or int8 with one scale per point."""
    feature_bits: int = Field(default=8, ge=2, le=8)
    """Bits of an int8 feature code (levels +-(2^(bits-1)-1)); zstd packs fewer bits smaller."""
    decoder_delta: bool = True
    """Send decoder weights as int8 deltas against the last weights the server agreed on."""
    decoder_full_codec: Literal["float16", "int8"] = "int8"
    """Full decoder weights (the first, and every tenth of an agent's own): float16 or int8."""
    zstd_level: int = Field(default=3, ge=0, le=22)
    """zstd level of the agent's messages of 1 kB or more; 0 sends them uncompressed."""
    jpeg_quality: int = Field(default=90, ge=1, le=100)
    """JPEG quality of the keyframe colour images sent to the server."""
    depth_codec: Literal["png", "zstd-delta"] = "zstd-delta"
    """Keyframe depth compression, both lossless: 16-bit PNG, or zstd-delta (a quarter smaller)."""
    depth_step_mm_per_m2: NonNegativeFloat = 0.5
    """Keyframe depth as inverse depth, in steps of this x depth² mm (0.1-50); 0: linear mm."""
    depth_step_noise_ratio: NonNegativeFloat = 2.0
    """The depth step is at least this x the measured noise sigma / depth², up to 1.5 (0: fixed)."""
    noisy_image_scale: float = Field(default=0.5, gt=0, le=1)
    """Largest keyframe image size (of the processed size) once merged while depth is noisy."""
    noisy_depth_mm_per_m2: PositiveFloat = 0.3
    """Depth is noisy when recent keyframes' median noise sigma / depth² reaches this (mm/m²)."""
    record: bool = False
    """Write every message sent, with its timing, and the keyframe images to agent_<id>/wire.rec."""
    record_mb: PositiveFloat = 1024.0
    """Largest wire recording (MiB); recording stops, with a warning, beyond it."""

    @field_validator("depth_step_mm_per_m2")
    @classmethod
    def _depth_step(cls, value: float) -> float:
        # uint16 inverse depth holds 1000 / (step x 65535) m to 2000 / step m: 0.15 m to 20 km
        # at 0.1, 0.3 m to 40 m at 50; outside that a sensor's near or far range is lost.
        if value != 0 and not 0.1 <= value <= 50:
            raise ValueError(f"depth step {value} mm/m²: expected 0 (linear mm) or 0.1-50")
        return value


class RunConfig(Section):
    """Process-level settings: output, device, seeds, logging."""

    seed: NonNegativeInt = 0
    """Seed of every random choice; a CPU run is reproducible."""
    device: str = "auto"
    """Compute device: auto, cpu, cuda or cuda:N."""
    out: Path = Path("runs")
    """Directory that holds run directories."""
    name: str | None = None
    """Run directory name under out; null = a timestamp."""
    log_level: Literal["debug", "info", "warning", "error"] = "info"
    """Least severe log level the daemons write."""
    num_threads: PositiveInt | Literal["auto"] | None = "auto"
    """Torch CPU threads: N; auto = usable cores / processes side by side; null = torch's."""
    deterministic: bool = True
    """Ask torch for deterministic algorithms (slower on GPU)."""
    schedule: Literal["concurrent", "lockstep"] = "concurrent"
    """concurrent: mapping on a thread of its own; lockstep: inline, repeats bit for bit."""
    rerun: Literal["save", "spawn", "connect"] | None = None
    """Agents log to Rerun while running (cpslam[viz]): save = agent_<id>/live.rrd; null = no."""
    rerun_url: str = "rerun+http://127.0.0.1:9876/proxy"
    """Viewer that rerun: connect sends to (Rerun's gRPC URL)."""
    rerun_every_s: PositiveFloat = 2.0
    """Seconds between logs of an agent's map points and trajectory line (poses: every frame)."""

    @field_validator("device")
    @classmethod
    def _device(cls, value: str) -> str:
        if not re.fullmatch(r"auto|cpu|cuda(?::\d+)?", value):
            raise ValueError(f"device {value!r}: expected auto, cpu, cuda or cuda:N")
        return value

    @field_validator("name")
    @classmethod
    def _name(cls, value: str | None) -> str | None:
        if value is not None and not re.fullmatch(r"[A-Za-z0-9_.-]+", value):
            raise ValueError(
                f"run name {value!r} must be one path component: letters, digits, '_', '.', '-'"
            )
        if value in (".", ".."):
            raise ValueError(f"run name {value!r} is not a directory name")
        return value
