"""Zenoh access control (the router's `access_control` section) for one cpslam session.

The server's Zenoh router checks every message crossing a link against these rules, by the
common name of the peer's client certificate (mutual TLS). Permissions are granted per identity
and everything else is denied:

- agent ``<a>`` may put its own messages (``agent/<a>/<topic>``), serve its own images
  (``agent/<a>/image/*``), hold its own liveliness token (``alive/agent/<a>``), and receive
  what the server sends it (``server/agent/<a>/*``: acks, updates, its group's decoders) and
  the server's presence. It cannot put on other agents' keys, on ``server/…`` (acks, updates,
  control), receive what the server sends another agent or another group, or query the status;
- the operator may query ``server/status``, put on ``server/control`` (finalise, shutdown)
  and watch the server's presence, nothing else;
- everyone receives subscriber declarations (key expressions only: Zenoh clients need them
  to send) and the server's presence token (``alive/server/<state>``), no one another peer's.

The key expressions come from `cpslam.protocol.keys`; "ingress" is what a peer sends the
router, "egress" what the router forwards to it. The server's own session is local to the
router, so the rules never restrict it.
"""

from __future__ import annotations

from typing import Any

from cpslam.protocol import keys

__all__ = ["ANY_SESSION", "access_control"]

ANY_SESSION = "*"
"""Session placeholder: the rules hold for every session (a one-chunk wildcard)."""

_PLACEHOLDER_AGENT = "AGENT"


def _base(session: str) -> str:
    return f"{keys.ROOT}/{session}"


def _keys_for(session: str, build: Any, *args: Any) -> str:
    # keys.* checks ids and rejects "*"; build with a valid id and put the session back.
    key = build("s", *args)
    assert key.startswith(f"{keys.ROOT}/s/")
    return _base(session) + key[len(f"{keys.ROOT}/s") :]


def _rule(rule_id: str, flow: str, messages: list[str], key_exprs: list[str]) -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": messages,
            "key_exprs": key_exprs}


def _agent_rules(session: str, agent_id: str) -> list[dict[str, Any]]:
    k = lambda build, *args: _keys_for(session, build, *args)  # noqa: E731
    own_topics = [k(keys.agent_topic, agent_id, topic) for topic in keys.AGENT_TOPICS]
    images = k(keys.agent_image_queryable, agent_id)
    to_agent = k(keys.server_agent_all, agent_id)
    alive_server = k(keys.alive_servers)
    p = f"agent {agent_id}: "
    return [
        _rule(p + "publish", "ingress", ["put"], own_topics),
        _rule(p + "serve images", "ingress", ["declare_queryable", "reply"], [images]),
        _rule(p + "presence", "ingress", ["liveliness_token"], [k(keys.alive_agent, agent_id)]),
        _rule(p + "subscribe", "ingress", ["declare_subscriber"], [to_agent]),
        _rule(p + "watch server", "ingress",
              ["declare_liveliness_subscriber", "liveliness_query"], [alive_server]),
        _rule(p + "receive", "egress", ["put"], [to_agent]),
        _rule(p + "image queries", "egress", ["query"], [images]),
    ]


def _operator_rules(session: str, operator: str) -> list[dict[str, Any]]:
    k = lambda build, *args: _keys_for(session, build, *args)  # noqa: E731
    status, control, alive_server = k(keys.server_status), k(keys.server_control), \
        k(keys.alive_servers)
    p = f"operator {operator}: "
    return [
        _rule(p + "status", "ingress", ["query"], [status]),
        _rule(p + "status replies", "egress", ["reply"], [status]),
        _rule(p + "control", "ingress", ["put"], [control]),
        _rule(p + "watch server", "ingress",
              ["declare_liveliness_subscriber", "liveliness_query"], [alive_server]),
    ]


def access_control(session: str, agent_ids: list[str], operators: list[str]) -> dict[str, Any]:
    """Zenoh's ``access_control`` object: deny by default, each certificate's common name
    bound to its own rules (see the module docstring). `session` may be `ANY_SESSION`."""
    if session != ANY_SESSION:
        keys.check_id(session, "session")
    names = [*agent_ids, *operators]
    for name in names:
        keys.check_id(name, "certificate name")
    if len(set(names)) != len(names):
        raise ValueError(f"agent and operator names must be distinct, got {names}")
    # A Zenoh client's declared publisher sends only while it knows of a matching subscriber,
    # so subscriber declarations (key expressions, no data) must reach every peer; Zenoh checks
    # a declared wildcard such as agent/*/* against whole rules, so this cannot be narrowed
    # to a peer's own keys. Presence: only the server's token (which peers wait for).
    base = _base(session)
    shared = [_rule("everyone: subscriber declarations", "egress", ["declare_subscriber"],
                    [f"{base}/**"]),
              _rule("everyone: server presence", "egress", ["liveliness_token"],
                    [_keys_for(session, keys.alive_servers)])]
    rules, subjects, policies = [*shared], [], []
    for name, own in [*((a, _agent_rules(session, a)) for a in agent_ids),
                      *((o, _operator_rules(session, o)) for o in operators)]:
        subject = f"cn {name}"
        subjects.append({"id": subject, "cert_common_names": [name]})
        rules.extend(own)
        policies.append({"id": f"policy {name}", "subjects": [subject],
                         "rules": [*(rule["id"] for rule in (*shared, *own))]})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}
