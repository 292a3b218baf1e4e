"""TLS and mutual TLS, with certificates made by the test: the server speaks only TLS, a client
certificate names the caller, and ogclient's --tls-* flags reach such a server."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import grpc
import pytest
from ogapi.v1 import mapping_pb2 as pb
from ogclient.__main__ import main as ogclient_main
from ogclient.connection import ClientError, Transport, connect
from ogserver import healthcheck

from .certificates import CertificateAuthority, make_ca
from .inprocess import Running, serving, settings
from .scene import FROZEN, PRESET, create_request


@pytest.fixture(scope="module")
def ca(tmp_path_factory: pytest.TempPathFactory) -> CertificateAuthority:
    return make_ca(tmp_path_factory.mktemp("ca"), clients=("alice", "bob"))


@pytest.fixture
def mutual(tmp_path: Path, ca: CertificateAuthority) -> Iterator[Running]:
    configured = settings(tmp_path)
    ca.serve(configured.access, mutual=True)
    with serving(configured) as running:
        yield running


def client(ca: CertificateAuthority, name: str | None) -> Transport:
    pem = ca.clients[name] if name else None
    return Transport(ca=str(ca.ca), cert=str(pem.cert) if pem else "", key=str(pem.key) if pem else "")


def test_tls_without_client_certificates(tmp_path: Path, ca: CertificateAuthority) -> None:
    configured = settings(tmp_path)
    ca.serve(configured.access)
    with serving(configured) as running:
        channel, stub = connect(running.address, 10, Transport(ca=str(ca.ca)))
        with channel:
            stub.CreateSession(create_request(FROZEN))
            assert len(stub.ListSessions(pb.ListSessionsRequest()).sessions) == 1  # open: one anonymous caller
        with pytest.raises(grpc.RpcError) as plaintext:
            running.stub.ListSessions(pb.ListSessionsRequest(), timeout=5)
        assert plaintext.value.code() == grpc.StatusCode.UNAVAILABLE


def test_client_certificates_name_the_callers(mutual: Running, ca: CertificateAuthority) -> None:
    alice_channel, alice = connect(mutual.address, 10, client(ca, "alice"))
    bob_channel, bob = connect(mutual.address, 10, client(ca, "bob"))
    with alice_channel, bob_channel:
        mine = alice.CreateSession(create_request(FROZEN)).session_id
        assert [info.session_id for info in alice.ListSessions(pb.ListSessionsRequest()).sessions] == [mine]
        assert not bob.ListSessions(pb.ListSessionsRequest()).sessions
    assert mutual.server.registry.sessions("cert:alice")[0].id == mine


def test_without_a_client_certificate_there_is_no_connection(mutual: Running, ca: CertificateAuthority) -> None:
    with pytest.raises(ClientError, match="over TLS"):
        connect(mutual.address, 1, client(ca, None))


def test_ogclient_flags(mutual: Running, ca: CertificateAuthority, tmp_path: Path,
                        capsys: pytest.CaptureFixture[str]) -> None:
    alice = ca.clients["alice"]
    flags = ["--server", mutual.address, "--tls-ca", str(ca.ca), "--tls-cert", str(alice.cert),
             "--tls-key", str(alice.key)]
    session_file = tmp_path / "session.json"
    assert ogclient_main([*flags, "create", "--preset", PRESET, "--session-out", str(session_file)]) == 0
    assert ogclient_main([*flags, "list"]) == 0
    assert "preset=sparse-fast" in capsys.readouterr().out
    assert ogclient_main(["--server", mutual.address, "--tls-ca", str(ca.ca), "--timeout", "2", "list"]) == 2


def test_the_container_health_check_speaks_tls(mutual: Running, ca: CertificateAuthority) -> None:
    alice = ca.clients["alice"]
    tls = ["--tls-ca", str(ca.ca), "--tls-cert", str(alice.cert), "--tls-key", str(alice.key)]
    assert healthcheck.main([mutual.address, *tls]) == 0
    assert healthcheck.main([mutual.address]) == 1
