"""docs/protocol.md cannot drift: its snippet, field tables and key table are checked here."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from cpslam import protocol as P
from cpslam.protocol import keys
from cpslam.protocol.samples import sample

DOC = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"
TEXT = DOC.read_text(encoding="utf-8")


def _python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", TEXT, flags=re.S)


def _section(heading_re: str) -> str:
    match = re.search(heading_re + r".*?\n(.*?)(?=\n#{2,3} |\Z)", TEXT, flags=re.S)
    assert match, f"no section matching {heading_re!r} in {DOC}"
    return match.group(1)


def _table_fields(text: str) -> list[list[str]]:
    """Field names of each markdown table in `text` (first column, in backticks)."""
    tables, current = [], []
    for line in text.splitlines():
        m = re.match(r"\| `(\w+)` \|", line)
        if m:
            current.append(m.group(1))
        elif current and not line.startswith("|"):
            tables.append(current)
            current = []
    if current:
        tables.append(current)
    return tables


def _snippet() -> dict:
    block = next(b for b in _python_blocks() if "def decode_keyframe" in b)
    namespace: dict = {}
    exec(compile(block, f"{DOC}:decode_keyframe", "exec"), namespace)  # noqa: S102
    return namespace


@pytest.mark.parametrize("first", [True, False])
def test_standalone_snippet_decodes_our_keyframe(first):
    msg = sample("keyframe", descriptor_dim=256)
    if first:
        msg = msg.model_copy(update={"T_prev_kf_kf": None})
    got = _snippet()["decode_keyframe"](P.encode(msg))
    assert set(got) == set(type(msg).model_fields)
    for name in type(msg).model_fields:
        want = getattr(msg, name)
        if isinstance(want, np.ndarray):
            assert got[name].dtype == want.dtype and np.array_equal(got[name], want), name
        else:
            assert got[name] == want, name


def test_standalone_snippet_refuses_other_messages():
    with pytest.raises(ValueError, match=f"not a version-{P.PROTOCOL_VERSION} keyframe"):
        _snippet()["decode_keyframe"](P.encode(sample("ack")))


def test_other_snippets_compile():
    for block in _python_blocks():
        compile(block, str(DOC), "exec")


@pytest.mark.parametrize("name", sorted(P.MESSAGE_TYPES))
def test_every_field_is_documented(name):
    cls = P.MESSAGE_TYPES[name]
    tables = _table_fields(_section(rf"### `{name}` — {cls.__name__}"))
    fields = [f for f in cls.model_fields if f not in ("type", "version")]
    assert tables and tables[0] == fields
    if cls is P.ServerUpdate:
        assert tables[1] == list(P.ForeignPoints.model_fields)


def test_size_caps_are_documented():
    for name, cls in P.MESSAGE_TYPES.items():
        cap = cls.max_bytes
        text = f"{cap // 2**20} MiB" if cap >= 2**20 else f"{cap // 1024} KiB"
        assert f"| `{name}` | `{cls.__name__}` | {text} |" in TEXT


def test_every_key_expression_is_documented():
    built = {
        keys.agent_keyframe("S", "A"),
        keys.agent_submap("S", "A"),
        keys.agent_decoder("S", "A"),
        keys.agent_frames("S", "A"),
        keys.agent_image("S", "A", 7),
        keys.agent_image_queryable("S", "A"),
        keys.server_agent_update("S", "A"),
        keys.server_agent_ack("S", "A"),
        keys.server_agent_refusal("S", "A"),
        keys.agent_topic("S", "A", "update_ack"),
        keys.server_agent_all("S", "A"),
        keys.all_server_agent("S"),
        keys.server_group_decoder("S", "G"),
        keys.all_group_decoders("S"),
        keys.server_status("S"),
        keys.server_control("S"),
        keys.alive_agent("S", "A"),
        keys.alive_agents("S"),
        keys.alive_server("S", 1),
        keys.alive_servers("S"),
        keys.alive_all("S"),
        keys.all_agents("S"),
        keys.all_agents_topic("S", "keyframe"),
        keys.run_barrier("S"),
    }
    for key in built:
        assert key.startswith("cpslam/S/")
        rel = key[len("cpslam/S/") :].replace("/A/", "/<agent>/").replace("/G/", "/<group>/")
        rel = re.sub(r"/A$", "/<agent>", rel).replace("/image/7", "/image/<kf>")
        rel = rel.replace("alive/server/1", "alive/server/<state>")
        assert f"`{rel}`" in TEXT, f"key {rel!r} is not in {DOC.name}"


def test_depth_delta_snippet_decodes_our_codec():
    from cpslam.protocol.depth_delta import encode_depth_delta

    block = next(b for b in _python_blocks() if "def decode_depth_delta" in b)
    namespace: dict = {}
    exec(compile(block, f"{DOC}:decode_depth_delta", "exec"), namespace)  # noqa: S102
    rng = np.random.default_rng(0)
    depth = np.cumsum(rng.integers(-3, 4, (30, 40)), axis=0) + 2000
    depth[rng.random(depth.shape) < 0.1] = 0  # holes: escapes on both of their sides
    depth[5, :] = 65535
    depth = depth.astype(np.uint16)
    got = namespace["decode_depth_delta"](encode_depth_delta(depth), 40, 30)
    assert got.dtype == np.uint16 and np.array_equal(got, depth)
