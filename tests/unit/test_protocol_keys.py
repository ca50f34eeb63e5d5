"""Key expressions: building, parsing back, and refusing ids that would break them."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cpslam.protocol import ProtocolError, keys

S, A = "demo", "agent-0"


def test_agent_keys():
    assert keys.agent_keyframe(S, A) == "cpslam/demo/agent/agent-0/keyframe"
    assert keys.agent_submap(S, A) == "cpslam/demo/agent/agent-0/submap"
    assert keys.agent_decoder(S, A) == "cpslam/demo/agent/agent-0/decoder"
    assert keys.agent_frames(S, A) == "cpslam/demo/agent/agent-0/frames"
    assert keys.agent_image(S, A, 12) == "cpslam/demo/agent/agent-0/image/12"
    assert keys.agent_image(S, A, np.int64(12)) == "cpslam/demo/agent/agent-0/image/12"
    assert keys.agent_image_queryable(S, A) == "cpslam/demo/agent/agent-0/image/*"


def test_server_and_liveliness_keys():
    assert keys.server_agent_update(S, A) == "cpslam/demo/server/agent/agent-0/update"
    assert keys.server_agent_ack(S, A) == "cpslam/demo/server/agent/agent-0/ack"
    assert keys.server_agent_all(S, A) == "cpslam/demo/server/agent/agent-0/*"
    assert keys.all_server_agent(S) == "cpslam/demo/server/agent/*/*"
    assert keys.server_group_decoder(S, "g_1") == "cpslam/demo/server/group/g_1/decoder"
    assert keys.all_group_decoders(S) == "cpslam/demo/server/group/*/decoder"
    assert keys.server_status(S) == "cpslam/demo/server/status"
    assert keys.server_control(S) == "cpslam/demo/server/control"
    assert keys.alive_agent(S, A) == "cpslam/demo/alive/agent/agent-0"
    assert keys.alive_agents(S) == "cpslam/demo/alive/agent/*"
    assert keys.alive_server(S, 42) == "cpslam/demo/alive/server/42"
    assert keys.alive_servers(S) == "cpslam/demo/alive/server/*"
    assert keys.parse_alive_server(S, keys.alive_server(S, 2**63 - 1)) == 2**63 - 1
    for bad in (0, -1, 2**63, "7"):
        with pytest.raises(ProtocolError):
            keys.alive_server(S, bad)
    assert keys.alive_all(S) == "cpslam/demo/alive/**"
    assert keys.run_barrier(S) == "cpslam/demo/run/barrier"


def test_wildcards():
    assert keys.all_agents_topic(S, "keyframe") == "cpslam/demo/agent/*/keyframe"
    assert keys.all_agents(S) == "cpslam/demo/agent/*/*"
    with pytest.raises(ProtocolError, match="agent topic"):
        keys.all_agents_topic(S, "image")


def _matches(pattern: str, key: str) -> bool:
    """Zenoh semantics for the wildcards we use: '*' one chunk, '**' any chunks."""
    regex = "/".join(
        ".+" if c == "**" else "[^/]+" if c == "*" else re.escape(c) for c in pattern.split("/")
    )
    return re.fullmatch(regex, key) is not None


def test_wildcards_match_exactly_their_keys():
    everything = [
        *(keys.agent_topic(S, A, t) for t in keys.AGENT_TOPICS),
        keys.agent_image(S, A, 3),
        keys.server_agent_update(S, A),
        keys.server_agent_ack(S, A),
        keys.server_group_decoder(S, "g"),
        keys.server_status(S),
        keys.server_control(S),
        keys.alive_agent(S, A),
        keys.alive_server(S, 7),
    ]
    hits = {k for k in everything if _matches(keys.all_agents(S), k)}
    assert hits == {keys.agent_topic(S, A, t) for t in keys.AGENT_TOPICS}
    hits = {k for k in everything if _matches(keys.alive_all(S), k)}
    assert hits == {keys.alive_agent(S, A), keys.alive_server(S, 7)}
    hits = {k for k in everything if _matches(keys.alive_servers(S), k)}
    assert hits == {keys.alive_server(S, 7)}
    assert [k for k in everything if _matches(keys.agent_image_queryable(S, A), k)] == [
        keys.agent_image(S, A, 3)
    ]
    assert [k for k in everything if _matches(keys.server_agent_all(S, A), k)] == [
        keys.server_agent_update(S, A),
        keys.server_agent_ack(S, A),
    ]


def test_parse_round_trips():
    for topic in keys.AGENT_TOPICS:
        assert keys.parse_agent_key(S, keys.agent_topic(S, A, topic)) == (A, topic)
    assert keys.parse_image_key(S, keys.agent_image(S, A, 2**31 - 1)) == (A, 2**31 - 1)
    assert keys.parse_server_agent_key(S, keys.server_agent_ack(S, A)) == (A, "ack")
    assert keys.parse_group_decoder(S, keys.server_group_decoder(S, "g")) == "g"
    assert keys.parse_alive_agent(S, keys.alive_agent(S, A)) == A


def test_key_subject_names_the_agent_or_group_of_a_key():
    for topic in keys.AGENT_TOPICS:
        assert keys.key_subject(S, keys.agent_topic(S, A, topic)) == ("agent", A, topic)
    assert keys.key_subject(S, keys.agent_image(S, A, 7)) == ("agent", A, "image")
    assert keys.key_subject(S, keys.server_agent_update(S, A)) == ("agent", A, "update")
    assert keys.key_subject(S, keys.server_agent_ack(S, A)) == ("agent", A, "ack")
    assert keys.key_subject(S, keys.server_group_decoder(S, "g")) == ("group", "g", "decoder")
    others = [keys.all_agents(S), keys.all_group_decoders(S), keys.agent_image_queryable(S, A),
              keys.server_status(S), keys.server_control(S), keys.alive_agent(S, A),
              keys.run_barrier(S), keys.agent_keyframe("other", A), "cpslam/demo",
              "elsewhere/agent/a/keyframe", None]
    for key in others:
        assert keys.key_subject(S, key) is None, key


@pytest.mark.parametrize(
    "parse, key",
    [
        (keys.parse_agent_key, "cpslam/other/agent/a/keyframe"),
        (keys.parse_agent_key, "cpslam/demo/agent/a/image/3"),
        (keys.parse_agent_key, "cpslam/demo/agent/a/unknown"),
        (keys.parse_agent_key, "cpslam/demo/agent/a*b/keyframe"),
        (keys.parse_image_key, "cpslam/demo/agent/a/image/-1"),
        (keys.parse_image_key, "cpslam/demo/agent/a/image/007"),
        (keys.parse_image_key, "cpslam/demo/agent/a/image/2147483648"),
        (keys.parse_image_key, "cpslam/demo/agent/a/image/x"),
        (keys.parse_server_agent_key, "cpslam/demo/server/agent/a/other"),
        (keys.parse_group_decoder, "cpslam/demo/server/group/g/update"),
        (keys.parse_alive_agent, "cpslam/demo/alive/server"),
        (keys.parse_alive_agent, b"cpslam/demo/alive/agent/a"),
        (keys.parse_alive_server, "cpslam/demo/alive/server"),
        (keys.parse_alive_server, "cpslam/demo/alive/server/0"),
        (keys.parse_alive_server, "cpslam/demo/alive/server/x"),
        (keys.parse_alive_server, "cpslam/demo/alive/server/9223372036854775808"),
        (keys.parse_alive_server, "cpslam/demo/alive/agent/a"),
    ],
)
def test_parse_rejects(parse, key):
    with pytest.raises(ProtocolError):
        parse(S, key)


@pytest.mark.parametrize(
    "bad", ["", "a/b", "a*", "$x", "a?b", "a#", "a b", "é", "a\n", "x" * 65, None, 3]
)
def test_bad_ids_are_refused(bad):
    with pytest.raises(ProtocolError, match="agent id must be"):
        keys.agent_keyframe(S, bad)
    with pytest.raises(ProtocolError, match="session must be"):
        keys.server_status(bad)


@pytest.mark.parametrize("bad", [-1, 2**31, True, 1.0, "3"])
def test_bad_keyframe_ids_are_refused(bad):
    with pytest.raises(ProtocolError, match="keyframe id"):
        keys.agent_image(S, A, bad)


@settings(max_examples=500, deadline=None)
@given(st.text(max_size=70), st.text(max_size=70))
def test_any_text_is_a_valid_id_or_refused(session, agent):
    valid = all(re.fullmatch(r"[A-Za-z0-9_-]{1,64}", x) for x in (session, agent))
    try:
        key = keys.agent_frames(session, agent)
    except ProtocolError:
        assert not valid
        return
    assert valid
    assert keys.parse_agent_key(session, key) == (agent, "frames")
    assert not set(agent) & set("/*$?#")


def _key_literals(path: Path) -> list[tuple[int, str]]:
    """(line, text) of string literals and f-strings in `path` that start with "cpslam/"."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    # An f-string counts once, by its leading text; its inner pieces are not literals.
    pieces = {id(v) for n in ast.walk(tree) if isinstance(n, ast.JoinedStr) for v in n.values}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.JoinedStr) and node.values:
            head = node.values[0]
            text = head.value if isinstance(head, ast.Constant) else ""
        elif isinstance(node, ast.Constant) and id(node) not in pieces:
            text = node.value
        else:
            continue
        if isinstance(text, str) and text.startswith(f"{keys.ROOT}/"):
            found.append((node.lineno, text))
    return found


def test_only_protocol_keys_spells_key_expressions():
    root = Path(__file__).resolve().parents[2]
    own = root / "protocol" / "keys.py"
    files = [p for folder in ("agent", "server", "common", "cpslam", "protocol")
             for p in sorted((root / folder).rglob("*.py")) if p.resolve() != own]
    assert len(files) > 20, f"source tree not found under {root}"
    offenders = [f"{p.relative_to(root)}:{line}: {text!r}" for p in files
                 for line, text in _key_literals(p)]
    assert not offenders, "build keys with cpslam.protocol.keys:\n" + "\n".join(offenders)


def test_key_literal_finder_sees_plain_and_f_strings(tmp_path: Path):
    src = tmp_path / "m.py"
    src.write_text('"""Docstring naming cpslam/x/agent/a/keyframe is prose."""\n'
                   'a = "cpslam/s/agent/a/keyframe"\nb = f"cpslam/{a}/run"\n'
                   'c = f"{a}/cpslam/"\nd = "cpslam.protocol"\n')
    assert [line for line, _ in _key_literals(src)] == [2, 3]


def test_protocol_imports_no_torch_zenoh_or_common():
    import subprocess
    import sys

    code = (
        "import sys, cpslam.protocol, cpslam.protocol.samples\n"
        "bad = [m for m in sys.modules if m.split('.')[0] in ('torch', 'zenoh')"
        " or m.startswith('cpslam.common')]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
