"""The sim's and the demo's HTTP client: where it connects, and its token and CA files."""

from __future__ import annotations

import pytest

from services.http_client import HttpClient, read_token
from services.map_server.config import ServerConfig


@pytest.mark.parametrize(
    "http, base",
    [
        ("127.0.0.1:8000", "http://127.0.0.1:8000"),
        ("0.0.0.0:8000", "http://127.0.0.1:8000"),  # every address: this machine's loopback
        ("[::]:8000", "http://[::1]:8000"),
        ("[::1]:9", "http://[::1]:9"),
        ("localhost:8000", "http://localhost:8000"),
    ],
)
def test_the_client_reaches_the_server_on_this_machine(http, base):
    assert HttpClient.for_server(ServerConfig(http=http), None, None) == HttpClient(base)


def test_tls_and_a_token_from_files(tmp_path):
    (tmp_path / "token").write_text("gmmap_abc\n")
    server = ServerConfig(http="127.0.0.1:8443", http_tls_cert="c", http_tls_key="k")
    client = HttpClient.for_server(server, str(tmp_path / "token"), None)
    assert client == HttpClient("https://127.0.0.1:8443", "gmmap_abc")


def test_bad_token_and_ca_files_are_named(tmp_path):
    server = ServerConfig()
    with pytest.raises(ValueError, match="--http-token: the server has tokens"):  # every request would be 401
        HttpClient.for_server(ServerConfig(http_tokens="tokens.txt"), None, None)
    with pytest.raises(ValueError, match=r"--http-token: cannot read .*absent"):
        read_token(tmp_path / "absent")
    (tmp_path / "two").write_text("gmmap_a gmmap_b")
    with pytest.raises(ValueError, match="must hold the token alone, got 2 words"):
        HttpClient.for_server(server, str(tmp_path / "two"), None)
    (tmp_path / "ca.pem").write_text("not a certificate")
    with pytest.raises(ValueError, match=r"--http-ca: .*ca.pem is not a PEM CA bundle"):
        HttpClient.for_server(server, None, str(tmp_path / "ca.pem"))
