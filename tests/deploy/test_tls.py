"""The deployment's mutual TLS: the router and client configs of ``docker/zenoh/`` with
certificates made by the ``openssl`` commands of docs/deployment.md, on a loopback TLS endpoint."""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.common.bus import Bus, BusError, NoResponder, QueryAnswer, ZenohOptions
from services.common.keys import Keys
from services.common.processes import free_tcp_endpoint
from tests.conftest import wait_until

ZENOH = Path(__file__).resolve().parents[2] / "docker" / "zenoh"
KEYS = Keys("tls")
PASSWORDS = {"operator": "op-secret", "kinematics": "kin-secret"}

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl CLI")


def _openssl(tls: Path, *args: str) -> None:
    subprocess.run(["openssl", *args], cwd=tls, check=True, capture_output=True)


def _certificates(tls: Path, ca: str = "ca") -> None:
    """A CA, a router certificate for 127.0.0.1 and a client certificate (the steps of docs/deployment.md)."""
    days = ("-days", "30")
    _openssl(tls, "req", "-x509", "-newkey", "rsa:2048", "-nodes", *days, "-subj", f"/CN={ca}",
             "-keyout", f"{ca}-key.pem", "-out", f"{ca}.pem")
    _openssl(tls, "req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=zenoh-router",
             "-keyout", "router-key.pem", "-out", "router.csr",
             "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1")
    _openssl(tls, "x509", "-req", "-in", "router.csr", "-CA", f"{ca}.pem", "-CAkey",
             f"{ca}-key.pem", "-CAcreateserial", *days, "-copy_extensions", "copy",
             "-out", "router-cert.pem")
    _openssl(tls, "req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=handkse-client",
             "-keyout", "client-key.pem", "-out", "client.csr",
             "-addext", "subjectAltName=DNS:handkse-client")
    _openssl(tls, "x509", "-req", "-in", "client.csr", "-CA", f"{ca}.pem", "-CAkey",
             f"{ca}-key.pem", "-CAcreateserial", *days, "-copy_extensions", "copy",
             "-out", "client-cert.pem")


@pytest.fixture
def deployment(tmp_path: Path) -> Iterator[tuple[str, Path]]:
    tls = tmp_path / "tls"
    tls.mkdir()
    _certificates(tls)
    creds = tmp_path / "credentials.txt"
    creds.write_text("".join(f"{u}:{p}\n" for u, p in PASSWORDS.items()))
    endpoint = "tls/" + free_tcp_endpoint().split("/", 1)[1]
    router = ZenohOptions(config_file=str(ZENOH / "router.json5"), mode="router",
                          listen=(endpoint,),
                          cfg=(f'transport/link/tls/listen_private_key:"{tls}/router-key.pem"',
                               f'transport/link/tls/listen_certificate:"{tls}/router-cert.pem"',
                               f'transport/link/tls/root_ca_certificate:"{tls}/ca.pem"',
                               f'transport/auth/usrpwd/dictionary_file:"{creds}"'))
    with Bus(router):
        yield endpoint, tls


def _client(endpoint: str, tls: Path, user: str, *, key: str = "client-key.pem",
            cert: str = "client-cert.pem", ca: str = "ca.pem") -> Bus:
    return Bus(ZenohOptions(
        config_file=str(ZENOH / "client.json5"), mode="client", connect=(endpoint,),
        multicast_scouting=False, connect_timeout_ms=3000,
        cfg=(f'transport/link/tls/root_ca_certificate:"{tls / ca}"',
             f'transport/link/tls/connect_private_key:"{tls / key}"',
             f'transport/link/tls/connect_certificate:"{tls / cert}"',
             f'transport/auth/usrpwd/user:"{user}"',
             f'transport/auth/usrpwd/password:"{PASSWORDS[user]}"')))


def test_clients_with_certificates_talk_over_mutual_tls(deployment: tuple[str, Path]) -> None:
    endpoint, tls = deployment
    with _client(endpoint, tls, "kinematics") as kinematics, \
            _client(endpoint, tls, "operator") as operator:
        kinematics.declare_queryable(KEYS.kinematics_model, lambda r: QueryAnswer(b"model"))

        def answered() -> bool:  # the declaration reaches the router asynchronously
            try:
                return operator.get(KEYS.kinematics_model, timeout=3.0)[0][1] == b"model"
            except NoResponder:
                return False

        wait_until(answered, 10, period=0.1, what="the model answered over mutual TLS")


def test_a_client_with_a_certificate_from_another_ca_is_refused(
        deployment: tuple[str, Path]) -> None:
    endpoint, tls = deployment
    other = tls / "other"
    other.mkdir()
    _certificates(other, ca="rogue")
    with pytest.raises(BusError, match="cannot open zenoh session"):
        # trusts the real router, but presents a certificate the router's CA did not sign
        _client(endpoint, tls, "operator", key="other/client-key.pem",
                cert="other/client-cert.pem")


def test_plain_tcp_is_not_served(deployment: tuple[str, Path]) -> None:
    endpoint, _ = deployment
    tcp = "tcp/" + endpoint.split("/", 1)[1]
    with pytest.raises(BusError, match="cannot open zenoh session"):
        Bus(ZenohOptions(mode="client", connect=(tcp,), multicast_scouting=False,
                         connect_timeout_ms=2000,
                         cfg=('transport/auth/usrpwd/user:"operator"',
                              f'transport/auth/usrpwd/password:"{PASSWORDS["operator"]}"')))
