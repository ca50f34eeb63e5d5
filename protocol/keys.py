"""Zenoh key expressions: the only place that builds or parses them.

Everything lives under ``cpslam/<session>/``::

    agent/<agent>/keyframe            KeyframeMsg       agent -> server (put)
    agent/<agent>/submap              SubmapDelta       agent -> server (put)
    agent/<agent>/decoder             DecoderWeights    agent -> server (put)
    agent/<agent>/frames              FramePoses        agent -> server (put)
    agent/<agent>/update_ack          UpdateAck         agent -> server (put)
    agent/<agent>/image/<kf>          KeyframeImage     server -> agent (get; agent answers)
    server/agent/<agent>/update       ServerUpdate      server -> agent (put)
    server/agent/<agent>/ack          Ack               server -> agent (put)
    server/agent/<agent>/refusal      Refusal           server -> agent (put)
    server/group/<group>/decoder      GroupDecoder      server -> agents (put)
    server/status                     Status            anyone -> server (get; server answers)
    server/control                    Control           operator -> server -> agents (put)
    alive/agent/<agent>               liveliness token of an agent
    alive/server/<state>              liveliness token of the server (its state id)
    run/barrier                       opaque marker     `cpslam run` only (in-process bus)

Ids (session, agent, group) are 1-64 characters of ``[A-Za-z0-9_-]``, so they never contain
the key-expression specials ``/ * $ ? #``; keyframe ids are non-negative ints.
"""

from __future__ import annotations

import operator
import re

from cpslam.protocol.errors import ProtocolError

__all__ = [
    "AGENT_TOPICS",
    "SERVER_AGENT_TOPICS",
    "ROOT",
    "check_id",
    "agent_keyframe",
    "agent_submap",
    "agent_decoder",
    "agent_frames",
    "agent_image",
    "agent_image_queryable",
    "agent_topic",
    "all_agents",
    "all_agents_topic",
    "server_agent_update",
    "server_agent_ack",
    "server_agent_refusal",
    "server_agent_all",
    "all_server_agent",
    "all_server_agent_topic",
    "server_agent_group_decoder",
    "server_group_decoder",
    "all_group_decoders",
    "server_status",
    "server_control",
    "alive_agent",
    "alive_agents",
    "alive_server",
    "alive_servers",
    "alive_all",
    "run_barrier",
    "parse_agent_key",
    "parse_image_key",
    "parse_server_agent_key",
    "parse_group_decoder",
    "parse_alive_agent",
    "parse_alive_server",
    "key_subject",
]

ROOT = "cpslam"
"""First chunk of every key expression."""

AGENT_TOPICS: tuple[str, ...] = ("keyframe", "submap", "decoder", "frames", "update_ack")
"""Topics an agent publishes on under ``agent/<agent>/``."""

SERVER_AGENT_TOPICS: tuple[str, ...] = ("update", "ack", "refusal", "group_decoder")
"""Topics the server publishes on under ``server/agent/<agent>/``."""

_ID_RE = re.compile(r"[A-Za-z0-9_-]{1,64}")
_KF_RE = re.compile(r"0|[1-9][0-9]{0,9}")
_MAX_KF = 2**31 - 1
_MAX_STATE_ID = 2**63 - 1


def check_id(value: object, what: str = "id") -> str:
    """Return `value` if it is a valid id (1-64 of ``[A-Za-z0-9_-]``), else raise ProtocolError."""
    if not isinstance(value, str) or not _ID_RE.fullmatch(value):
        raise ProtocolError(
            f"{what} must be 1-64 characters of [A-Za-z0-9_-] (no '/', '*', '$', '?', '#'), "
            f"got {value!r:.80}"
        )
    return value


def _kf(kf_id: object) -> int:
    try:
        value = operator.index(kf_id)  # accepts numpy ints, refuses floats and strings
    except TypeError:
        raise ProtocolError(f"keyframe id must be an int, got {kf_id!r:.40}") from None
    if isinstance(kf_id, bool) or not 0 <= value <= _MAX_KF:
        raise ProtocolError(f"keyframe id must be an int in [0, {_MAX_KF}], got {kf_id!r:.40}")
    return value


def _base(session: str) -> str:
    return f"{ROOT}/{check_id(session, 'session')}"


# --- agent -> server -------------------------------------------------------------------------


def agent_topic(session: str, agent_id: str, topic: str) -> str:
    """``cpslam/<session>/agent/<agent>/<topic>`` for a topic in `AGENT_TOPICS`."""
    if topic not in AGENT_TOPICS:
        raise ProtocolError(f"agent topic must be one of {AGENT_TOPICS}, got {topic!r:.40}")
    return f"{_base(session)}/agent/{check_id(agent_id, 'agent id')}/{topic}"


def agent_keyframe(session: str, agent_id: str) -> str:
    """Key on which an agent puts its `KeyframeMsg`s."""
    return agent_topic(session, agent_id, "keyframe")


def agent_submap(session: str, agent_id: str) -> str:
    """Key on which an agent puts its `SubmapDelta`s."""
    return agent_topic(session, agent_id, "submap")


def agent_decoder(session: str, agent_id: str) -> str:
    """Key on which an agent puts its `DecoderWeights`."""
    return agent_topic(session, agent_id, "decoder")


def agent_frames(session: str, agent_id: str) -> str:
    """Key on which an agent puts its `FramePoses`."""
    return agent_topic(session, agent_id, "frames")


def all_agents_topic(session: str, topic: str) -> str:
    """Wildcard over every agent for one topic, e.g. ``cpslam/s/agent/*/keyframe``."""
    if topic not in AGENT_TOPICS:
        raise ProtocolError(f"agent topic must be one of {AGENT_TOPICS}, got {topic!r:.40}")
    return f"{_base(session)}/agent/*/{topic}"


def all_agents(session: str) -> str:
    """Wildcard over every agent and every topic: ``cpslam/<session>/agent/*/*``.

    It does not match image keys (three chunks after the agent id), so a subscriber on it
    sees only published messages.
    """
    return f"{_base(session)}/agent/*/*"


def agent_image(session: str, agent_id: str, kf_id: int) -> str:
    """Key the server queries for one keyframe's images: ``…/agent/<agent>/image/<kf>``."""
    return f"{_base(session)}/agent/{check_id(agent_id, 'agent id')}/image/{_kf(kf_id)}"


def agent_image_queryable(session: str, agent_id: str) -> str:
    """Key expression an agent declares its image queryable on: ``…/agent/<agent>/image/*``."""
    return f"{_base(session)}/agent/{check_id(agent_id, 'agent id')}/image/*"


# --- server -> agents ------------------------------------------------------------------------


def server_agent_update(session: str, agent_id: str) -> str:
    """Key on which the server puts `ServerUpdate`s for one agent."""
    return f"{_base(session)}/server/agent/{check_id(agent_id, 'agent id')}/update"


def server_agent_ack(session: str, agent_id: str) -> str:
    """Key on which the server puts `Ack`s for one agent."""
    return f"{_base(session)}/server/agent/{check_id(agent_id, 'agent id')}/ack"


def server_agent_refusal(session: str, agent_id: str) -> str:
    """Key on which the server puts a `Refusal` of one of the agent's incarnations."""
    return f"{_base(session)}/server/agent/{check_id(agent_id, 'agent id')}/refusal"


def server_agent_group_decoder(session: str, agent_id: str) -> str:
    """Key on which the server puts its group's shared `GroupDecoder` for one member."""
    return f"{_base(session)}/server/agent/{check_id(agent_id, 'agent id')}/group_decoder"


def server_agent_all(session: str, agent_id: str) -> str:
    """Wildcard over everything the server sends one agent: ``…/server/agent/<agent>/*``."""
    return f"{_base(session)}/server/agent/{check_id(agent_id, 'agent id')}/*"


def all_server_agent(session: str) -> str:
    """Wildcard over everything the server sends any agent: ``…/server/agent/*/*``."""
    return f"{_base(session)}/server/agent/*/*"


def all_server_agent_topic(session: str, topic: str) -> str:
    """Wildcard over every agent for one server topic, e.g. ``cpslam/s/server/agent/*/ack``."""
    if topic not in SERVER_AGENT_TOPICS:
        raise ProtocolError(f"server topic must be one of {SERVER_AGENT_TOPICS}, "
                            f"got {topic!r:.40}")
    return f"{_base(session)}/server/agent/*/{topic}"


def server_group_decoder(session: str, group_id: str) -> str:
    """Key on which the server also puts a group's shared `GroupDecoder`, for observers (the
    members get it on their own keys, `server_agent_group_decoder`)."""
    return f"{_base(session)}/server/group/{check_id(group_id, 'group id')}/decoder"


def all_group_decoders(session: str) -> str:
    """Wildcard over every group's decoder: ``…/server/group/*/decoder``."""
    return f"{_base(session)}/server/group/*/decoder"


def server_status(session: str) -> str:
    """Key of the server's status queryable (replies with a `Status`)."""
    return f"{_base(session)}/server/status"


def server_control(session: str) -> str:
    """Key for `Control` messages (finalise, shutdown)."""
    return f"{_base(session)}/server/control"


# --- liveliness ------------------------------------------------------------------------------


def alive_agent(session: str, agent_id: str) -> str:
    """Liveliness token key of one agent."""
    return f"{_base(session)}/alive/agent/{check_id(agent_id, 'agent id')}"


def alive_agents(session: str) -> str:
    """Wildcard over every agent's liveliness token."""
    return f"{_base(session)}/alive/agent/*"


def alive_server(session: str, state_id: int) -> str:
    """Liveliness token key of the server holding the state `state_id` (`parse_alive_server`):
    an agent that sees another id come up knows the server lost what it had acknowledged."""
    if not isinstance(state_id, int) or not 0 < state_id <= _MAX_STATE_ID:
        raise ProtocolError(f"server state id must be an int in [1, {_MAX_STATE_ID}], "
                            f"got {state_id!r:.40}")
    return f"{_base(session)}/alive/server/{state_id}"


def alive_servers(session: str) -> str:
    """Wildcard over the server's liveliness token (whatever its state id)."""
    return f"{_base(session)}/alive/server/*"


def alive_all(session: str) -> str:
    """Wildcard over every liveliness token of the session (agents and server)."""
    return f"{_base(session)}/alive/**"


# --- in-process harness ----------------------------------------------------------------------


def run_barrier(session: str) -> str:
    """Key of `cpslam run`'s lock-step barrier marker (in-memory bus only, never on a network)."""
    return f"{_base(session)}/run/barrier"


# --- parsing ---------------------------------------------------------------------------------


def _chunks(session: str, key: object, what: str) -> list[str]:
    if not isinstance(key, str):
        raise ProtocolError(f"{what}: key must be a str, got {type(key).__name__}")
    prefix = _base(session) + "/"
    if not key.startswith(prefix):
        raise ProtocolError(f"{what}: key {key!r:.120} is not under {prefix!r}")
    return key[len(prefix) :].split("/")


def parse_agent_key(session: str, key: str) -> tuple[str, str]:
    """(agent id, topic) from ``cpslam/<session>/agent/<agent>/<topic>``."""
    parts = _chunks(session, key, "agent key")
    if len(parts) != 3 or parts[0] != "agent" or parts[2] not in AGENT_TOPICS:
        raise ProtocolError(f"agent key: expected agent/<id>/<topic>, got {key!r:.120}")
    return check_id(parts[1], "agent id"), parts[2]


def parse_image_key(session: str, key: str) -> tuple[str, int]:
    """(agent id, keyframe id) from ``cpslam/<session>/agent/<agent>/image/<kf>``."""
    parts = _chunks(session, key, "image key")
    if len(parts) != 4 or parts[0] != "agent" or parts[2] != "image":
        raise ProtocolError(f"image key: expected agent/<id>/image/<kf>, got {key!r:.120}")
    if not _KF_RE.fullmatch(parts[3]) or int(parts[3]) > _MAX_KF:
        raise ProtocolError(f"image key: keyframe id must be an int in [0, {_MAX_KF}]")
    return check_id(parts[1], "agent id"), int(parts[3])


def parse_server_agent_key(session: str, key: str) -> tuple[str, str]:
    """(agent id, topic) from ``cpslam/<session>/server/agent/<agent>/<topic>``."""
    parts = _chunks(session, key, "server key")
    if len(parts) != 4 or parts[:2] != ["server", "agent"] or parts[3] not in SERVER_AGENT_TOPICS:
        raise ProtocolError(f"server key: expected server/agent/<id>/<topic>, got {key!r:.120}")
    return check_id(parts[2], "agent id"), parts[3]


def parse_group_decoder(session: str, key: str) -> str:
    """Group id from ``cpslam/<session>/server/group/<group>/decoder``."""
    parts = _chunks(session, key, "group key")
    if len(parts) != 4 or parts[:2] != ["server", "group"] or parts[3] != "decoder":
        raise ProtocolError(f"group key: expected server/group/<id>/decoder, got {key!r:.120}")
    return check_id(parts[2], "group id")


def parse_alive_agent(session: str, key: str) -> str:
    """Agent id from a liveliness key ``cpslam/<session>/alive/agent/<agent>``."""
    parts = _chunks(session, key, "liveliness key")
    if len(parts) != 3 or parts[:2] != ["alive", "agent"]:
        raise ProtocolError(f"liveliness key: expected alive/agent/<id>, got {key!r:.120}")
    return check_id(parts[2], "agent id")


def parse_alive_server(session: str, key: str) -> int:
    """Server state id from a liveliness key ``cpslam/<session>/alive/server/<state>``."""
    parts = _chunks(session, key, "liveliness key")
    if (len(parts) != 3 or parts[:2] != ["alive", "server"] or not parts[2].isdigit()
            or not 0 < int(parts[2]) <= _MAX_STATE_ID):
        raise ProtocolError(f"liveliness key: expected alive/server/<state id in [1, "
                            f"{_MAX_STATE_ID}]>, got {key!r:.120}")
    return int(parts[2])


def key_subject(session: str, key: object) -> tuple[str, str, str] | None:
    """Whom a concrete key of `session` concerns, for traffic accounting.

    ``("agent", agent, topic)`` for ``agent/<agent>/<topic>``, ``agent/<agent>/image/<kf>``
    (topic ``"image"``) and ``server/agent/<agent>/<topic>``; ``("group", group, "decoder")``
    for ``server/group/<group>/decoder``; None for anything else (status, control,
    liveliness, wildcards, other sessions, malformed keys).
    """
    if not isinstance(key, str) or not key.startswith(_base(session) + "/"):
        return None
    parsers = (
        lambda: ("agent", *parse_agent_key(session, key)),
        lambda: ("agent", parse_image_key(session, key)[0], "image"),
        lambda: ("agent", *parse_server_agent_key(session, key)),
        lambda: ("group", parse_group_decoder(session, key), "decoder"),
    )
    for parse in parsers:
        try:
            return parse()
        except ProtocolError:
            continue
    return None
