"""Zenoh's own security settings for a `ZenohBus`: TLS / mutual TLS, user-password
authentication, access control and a base Zenoh JSON5 file.

Nothing here does cryptography: the values become Zenoh config keys
(``transport/link/tls/…``, ``transport/auth/usrpwd/…``, ``access_control``), and Zenoh's TLS
(rustls) and access control do the work. Files are checked when the bus opens, so a wrong path
is reported by the field that named it rather than as a Zenoh handshake failure.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zenoh

if TYPE_CHECKING:
    from cpslam.common.config import TransportConfig

__all__ = ["ZenohSecurity", "SECURE_PROTOCOLS", "certificate_name"]

SECURE_PROTOCOLS = ("tls", "quic")
"""Endpoint protocols that run over TLS and so need a CA (and a certificate to listen)."""


@dataclass(frozen=True)
class ZenohSecurity:
    """Security settings handed to Zenoh (fields as in `TransportConfig`'s tls_*, auth_*,
    access_control and zenoh_config, which document them)."""

    root_ca: Path | None = None
    cert: Path | None = None
    key: Path | None = None
    mtls: bool = False
    verify_name: bool = True
    auth_user: str | None = None
    auth_password_file: Path | None = None
    auth_dictionary: Path | None = None
    access_control: Path | None = None
    zenoh_config: Path | None = None

    @classmethod
    def from_transport(cls, transport: TransportConfig) -> ZenohSecurity:
        """The settings of a config's `transport` section."""
        return cls(
            root_ca=transport.tls_root_ca, cert=transport.tls_cert, key=transport.tls_key,
            mtls=transport.tls_mtls, verify_name=transport.tls_verify_name,
            auth_user=transport.auth_user, auth_password_file=transport.auth_password_file,
            auth_dictionary=transport.auth_dictionary,
            access_control=transport.access_control, zenoh_config=transport.zenoh_config,
        )

    def base_config(self) -> zenoh.Config:
        """The `zenoh_config` file, or Zenoh's defaults."""
        if self.zenoh_config is None:
            return zenoh.Config()
        path = _readable(self.zenoh_config, "transport.zenoh_config")
        try:
            return zenoh.Config.from_file(str(path))
        except zenoh.ZError as exc:
            raise ValueError(f"transport.zenoh_config {path}: not a valid Zenoh config: "
                             f"{exc}") from exc

    def settings(self, mode: str, endpoints: list[str]) -> dict[str, Any]:
        """Zenoh config keys for these settings, checked against the endpoints in use."""
        out: dict[str, Any] = {}
        if self.root_ca is not None:
            out["transport/link/tls/root_ca_certificate"] = str(
                _readable(self.root_ca, "transport.tls_root_ca"))
        if self.cert is not None and self.key is not None:
            cert = str(_readable(self.cert, "transport.tls_cert"))
            key = str(_readable(self.key, "transport.tls_key"))
            # One certificate serves both directions: a server listens with it (and may connect
            # to a router), a client presents it for mutual TLS.
            for side in ("listen", "connect"):
                out[f"transport/link/tls/{side}_certificate"] = cert
                out[f"transport/link/tls/{side}_private_key"] = key
        if self.root_ca is not None or self.cert is not None or self.mtls:
            out["transport/link/tls/enable_mtls"] = self.mtls
            out["transport/link/tls/verify_name_on_connect"] = self.verify_name
        if self.auth_user is not None and self.auth_password_file is not None:
            out["transport/auth/usrpwd/user"] = self.auth_user
            out["transport/auth/usrpwd/password"] = _password(self.auth_password_file)
        if self.auth_dictionary is not None:
            out["transport/auth/usrpwd/dictionary_file"] = str(
                _readable(self.auth_dictionary, "transport.auth_dictionary"))
        if self.access_control is not None:
            out["access_control"] = _access_control(self.access_control)
        self._check(mode, endpoints)
        return out

    def _check(self, mode: str, endpoints: list[str]) -> None:
        if self.zenoh_config is not None:
            return  # the file may hold the TLS settings; Zenoh reports what is missing
        secure = [e for e in endpoints if e.split("/", 1)[0] in SECURE_PROTOCOLS]
        if secure and self.root_ca is None:
            raise ValueError(f"endpoints {secure} use TLS: set transport.tls_root_ca (the CA "
                             "certificate) or a transport.zenoh_config holding Zenoh's "
                             "transport/link/tls settings")
        if secure and mode != "client" and self.cert is None:
            raise ValueError(f"listening on {secure} needs transport.tls_cert and "
                             "transport.tls_key (the server's certificate)")
        if secure and self.mtls and self.cert is None:
            raise ValueError("transport.tls_mtls needs transport.tls_cert and "
                             "transport.tls_key (this process's certificate)")


def _readable(path: Path, field: str) -> Path:
    path = Path(path).expanduser()
    if not path.is_file():
        raise ValueError(f"{field}: {path} is not a readable file")
    return path


def _password(path: Path) -> str:
    lines = _readable(path, "transport.auth_password_file").read_text("utf-8").splitlines()
    if not lines or not lines[0]:
        raise ValueError(f"transport.auth_password_file {path}: the first line must hold "
                         "the password")
    return lines[0]


def _access_control(path: Path) -> dict[str, Any]:
    """The access_control object of a JSON5 file, parsed by Zenoh itself (JSON5 with
    comments and trailing commas) by reading it as a config holding only that section."""
    path = _readable(path, "transport.access_control")
    try:
        conf = zenoh.Config.from_json5(
            "{access_control: " + path.read_text("utf-8") + "}")
    except zenoh.ZError as exc:
        raise ValueError(f"transport.access_control {path}: not a valid Zenoh access_control "
                         f"object: {exc}") from exc
    section = json.loads(conf.get_json("access_control"))
    if not section.get("enabled"):
        raise ValueError(f"transport.access_control {path}: 'enabled' must be true (a file "
                         "that does not enable access control would silently allow all)")
    return section


def certificate_name(path: Path) -> str:
    """The common name of a PEM certificate: the identity Zenoh's access control matches
    (`cert_common_names`). Raises ValueError naming the file when it has none."""
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    try:
        cert = x509.load_pem_x509_certificate(Path(path).read_bytes())
    except (OSError, ValueError) as exc:
        raise ValueError(f"transport.tls_cert {path}: not a readable PEM certificate "
                         f"({exc})") from exc
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    if not names:
        raise ValueError(f"transport.tls_cert {path}: the certificate has no common name")
    return str(names[0].value)
