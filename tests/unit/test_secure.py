"""`cpslam secure init` (certificates, ACL, overlays) and the transport security settings
handed to Zenoh (TLS files, user-password authentication, access control, base config)."""

from __future__ import annotations

import json
import stat
import time
from pathlib import Path

import pytest
import zenoh
from cryptography import x509
from cryptography.x509.oid import NameOID
from typer.testing import CliRunner

from cpslam.cli import app
from cpslam.common.bus import BusError, ZenohBus, ZenohSecurity, zenoh_config
from cpslam.common.config import ConfigError, load_config
from cpslam.demo import free_port
from cpslam.tools.secure.acl import access_control
from cpslam.tools.secure.bundle import write_bundle


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("secure")
    write_bundle(out, ["agent-0", "agent-1"], server_names=("server.lan", "10.0.0.5"),
                 port=7450, session="lab", install_dir=Path("/etc/cpslam"))
    return out


def _cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def test_certificates_are_signed_by_the_ca_and_named(bundle: Path) -> None:
    ca = _cert(bundle / "ca.pem")
    for name in ("server", "agent-0", "agent-1", "operator"):
        cert = _cert(bundle / f"{name}.pem")
        cert.verify_directly_issued_by(ca)
        assert stat.S_IMODE((bundle / f"{name}-key.pem").stat().st_mode) == 0o600
        if name != "server":
            cn = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value
            assert cn == name
    san = _cert(bundle / "server.pem").extensions.get_extension_for_class(
        x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.DNSName) == ["server.lan"]
    assert [str(ip) for ip in san.get_values_for_type(x509.IPAddress)] == ["10.0.0.5"]
    assert stat.S_IMODE((bundle / "ca-key.pem").stat().st_mode) == 0o600


def test_overlays_load_and_name_the_install_folder(bundle: Path) -> None:
    server = load_config("tiny", bundle / "server.yaml", env={}).transport
    assert server.listen == ["tls/0.0.0.0:7450"] and server.tls_mtls
    assert server.access_control == Path("/etc/cpslam/acl.json5")
    assert server.tls_cert == Path("/etc/cpslam/server.pem")
    agent = load_config("tiny", bundle / "agent-1.yaml", env={}).transport
    assert agent.connect == ["tls/server.lan:7450"] and agent.session == "lab"
    assert agent.tls_key == Path("/etc/cpslam/agent-1-key.pem")
    assert agent.tls_root_ca == Path("/etc/cpslam/ca.pem")


def _allowed(acl: dict, name: str, flow: str, message: str) -> list[str]:
    """Key expressions `name` is allowed `message` on in `flow`."""
    (policy,) = [p for p in acl["policies"] if p["subjects"] == [f"cn {name}"]]
    rules = {r["id"]: r for r in acl["rules"]}
    return sorted(k for rid in policy["rules"] for k in rules[rid]["key_exprs"]
                  if flow in rules[rid]["flows"] and message in rules[rid]["messages"])


def test_acl_binds_each_agent_to_its_own_keys() -> None:
    acl = access_control("lab", ["agent-0", "agent-1"], ["operator"])
    assert acl["default_permission"] == "deny" and acl["enabled"]
    assert _allowed(acl, "agent-1", "ingress", "put") == [
        f"cpslam/lab/agent/agent-1/{t}"
        for t in ("decoder", "frames", "keyframe", "submap", "update_ack")]
    assert _allowed(acl, "agent-1", "ingress", "liveliness_token") == [
        "cpslam/lab/alive/agent/agent-1"]
    assert _allowed(acl, "agent-1", "ingress", "declare_queryable") == [
        "cpslam/lab/agent/agent-1/image/*"]
    assert _allowed(acl, "agent-1", "ingress", "query") == []  # no status
    assert _allowed(acl, "operator", "ingress", "put") == ["cpslam/lab/server/control"]
    assert _allowed(acl, "operator", "ingress", "query") == ["cpslam/lab/server/status"]
    received = _allowed(acl, "agent-1", "egress", "put")
    assert received == ["cpslam/lab/server/agent/agent-1/*"]
    text = json.dumps([r for r in acl["rules"] if r["id"].startswith("agent agent-1")])
    assert "agent-0" not in text
    # Zenoh itself accepts the section.
    zenoh.Config().insert_json5("access_control", json.dumps(acl))


def test_acl_refuses_bad_names() -> None:
    with pytest.raises(ValueError, match="distinct"):
        access_control("*", ["a", "a"], ["operator"])
    with pytest.raises(Exception, match="certificate name"):
        access_control("*", ["agent/0"], ["operator"])


def test_security_settings_become_zenoh_keys(bundle: Path) -> None:
    sec = ZenohSecurity(root_ca=bundle / "ca.pem", cert=bundle / "agent-0.pem",
                        key=bundle / "agent-0-key.pem", mtls=True,
                        access_control=bundle / "acl.json5")
    conf = json.loads(str(zenoh_config("client", connect=["tls/server.lan:7450"],
                                       security=sec)))
    tls = conf["transport"]["link"]["tls"]
    assert tls["connect_certificate"] == str(bundle / "agent-0.pem")
    assert tls["enable_mtls"] is True and tls["verify_name_on_connect"] is True
    assert conf["access_control"]["default_permission"] == "deny"


def test_security_errors_name_the_field(tmp_path: Path, bundle: Path) -> None:
    with pytest.raises(ValueError, match="transport.tls_root_ca"):
        zenoh_config("client", connect=["tls/h:7447"])
    with pytest.raises(ValueError, match="transport.tls_cert"):
        zenoh_config("router", listen=["quic/0.0.0.0:7447"],
                     security=ZenohSecurity(root_ca=bundle / "ca.pem"))
    with pytest.raises(ValueError, match="transport.tls_root_ca: .*missing.pem"):
        zenoh_config("client", connect=["tls/h:7447"],
                     security=ZenohSecurity(root_ca=tmp_path / "missing.pem"))
    off = tmp_path / "off.json5"
    off.write_text("{enabled: false, default_permission: 'allow'}")
    with pytest.raises(ValueError, match="'enabled' must be true"):
        zenoh_config("router", security=ZenohSecurity(access_control=off))
    with pytest.raises(ConfigError, match="tls_cert and tls_key"):
        load_config("tiny", overrides=["transport.tls_cert=/x.pem"], env={})


def test_base_zenoh_config_is_applied_under_cpslam_keys(tmp_path: Path) -> None:
    base = tmp_path / "zenoh.json5"
    base.write_text("{ mode: 'peer', // a comment\n  transport: {link: {tx: {batch_size: 8192}}},"
                    " listen: {endpoints: ['tcp/127.0.0.1:1']} }")
    conf = json.loads(str(zenoh_config("client", connect=["tcp/127.0.0.1:7447"],
                                       security=ZenohSecurity(zenoh_config=base))))
    assert conf["transport"]["link"]["tx"]["batch_size"] == 8192  # from the file
    assert conf["mode"] == "client"  # cpslam's setting wins
    bad = tmp_path / "bad.json5"
    bad.write_text("{ nonsense_key: 1 }")
    with pytest.raises(ValueError, match="transport.zenoh_config"):
        zenoh_config("client", connect=["tcp/127.0.0.1:7447"],
                     security=ZenohSecurity(zenoh_config=bad))


def test_user_password_authentication(tmp_path: Path) -> None:
    (tmp_path / "users").write_text("alice:secret\n")
    (tmp_path / "good").write_text("secret\n")
    (tmp_path / "bad").write_text("guess\n")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with ZenohBus(mode="router", listen=[endpoint],
                  security=ZenohSecurity(auth_dictionary=tmp_path / "users")):
        ZenohBus(mode="client", connect=[endpoint], open_timeout_s=2.0, security=ZenohSecurity(
            auth_user="alice", auth_password_file=tmp_path / "good")).close()
        for sec in (ZenohSecurity(auth_user="alice", auth_password_file=tmp_path / "bad"),
                    ZenohSecurity()):
            with pytest.raises(BusError):
                ZenohBus(mode="client", connect=[endpoint], open_timeout_s=0.5, security=sec)


def test_secure_init_command(tmp_path: Path) -> None:
    runner = CliRunner()
    out = tmp_path / "s"
    done = runner.invoke(app, ["secure", "init", "--agents", "3", "--out", str(out)])
    assert done.exit_code == 0, done.output
    assert sorted(p.name for p in out.glob("*.yaml")) == [
        "agent-0.yaml", "agent-1.yaml", "agent-2.yaml", "operator.yaml", "server.yaml"]
    again = runner.invoke(app, ["secure", "init", "--out", str(out)])
    assert again.exit_code == 2 and "--overwrite" in again.output
    named = runner.invoke(app, ["secure", "init", "--agent-id", "robot-1", "--operator",
                                "robot-1", "--out", str(tmp_path / "t")])
    assert named.exit_code == 2 and "distinct" in named.output


def _mtls(bundle: Path, name: str) -> ZenohSecurity:
    return ZenohSecurity(root_ca=bundle / "ca.pem", cert=bundle / f"{name}.pem",
                         key=bundle / f"{name}-key.pem", mtls=True)


@pytest.mark.parametrize("protocol", ["tls", "quic"])
def test_mutual_tls_endpoints(tmp_path: Path, protocol: str) -> None:
    write_bundle(tmp_path, ["agent-0"])  # server names: localhost, 127.0.0.1
    endpoint = f"{protocol}/localhost:{free_port()}"
    with ZenohBus(mode="router", listen=[endpoint], security=_mtls(tmp_path, "server")) as srv:
        sub = srv.subscribe("t/**", queue_size=8)
        with ZenohBus(mode="client", connect=[endpoint], open_timeout_s=5.0,
                      security=_mtls(tmp_path, "agent-0")) as client:
            deadline = time.monotonic() + 10
            sample = None
            while sample is None and time.monotonic() < deadline:
                client.publish("t/x", b"over " + protocol.encode())
                sample = sub.get(timeout=0.2)
            assert sample is not None and sample.payload == b"over " + protocol.encode()
        # Trusting the CA is not enough: mutual TLS wants a client certificate.
        with pytest.raises(BusError):
            ZenohBus(mode="client", connect=[endpoint], open_timeout_s=0.5,
                     security=ZenohSecurity(root_ca=tmp_path / "ca.pem"))
        # A certificate of another CA is refused too.
        other = tmp_path / "other"
        write_bundle(other, ["agent-0"])
        with pytest.raises(BusError):
            ZenohBus(mode="client", connect=[endpoint], open_timeout_s=0.5,
                     security=_mtls(other, "agent-0"))


def test_agent_id_must_be_the_certificate_name(bundle: Path, tmp_path: Path) -> None:
    from cpslam.agent_cli import app as agent_app

    files = {"tls_cert": "agent-0.pem", "tls_key": "agent-0-key.pem", "tls_root_ca": "ca.pem"}
    sets = [arg for key, name in files.items()
            for arg in ("--set", f"transport.{key}={bundle / name}")]
    done = CliRunner().invoke(agent_app, ["--config", str(bundle / "agent-0.yaml"), "--agent-id",
                                          "agent-1", "--seq", str(tmp_path), *sets])
    assert done.exit_code == 2, done.output
    assert "differs from the name 'agent-0'" in done.output
