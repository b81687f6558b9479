"""The server's HTTP settings: addresses, what counts as loopback, and secure by default."""

from __future__ import annotations

import pytest

from services import cli
from services.cli_flags import resolve_config
from services.config import ConfigError, load_config
from services.map_server.config import ServerConfig, is_loopback, split_address

SECURE = {"http_tls_cert": "cert.pem", "http_tls_key": "key.pem", "http_tokens": "tokens.txt"}


def resolved(*argv: str) -> ServerConfig:
    return resolve_config(cli.build_parser().parse_args(["server", *argv])).server


@pytest.mark.parametrize(
    "address, host, port",
    [
        ("127.0.0.1:8000", "127.0.0.1", 8000),
        (":8000", "127.0.0.1", 8000),
        ("0.0.0.0:80", "0.0.0.0", 80),
        ("[::1]:8000", "::1", 8000),
        ("[::]:8000", "::", 8000),
        ("map.example:443", "map.example", 443),
    ],
)
def test_addresses(address, host, port):
    assert split_address(address) == (host, port)


@pytest.mark.parametrize("address", ["8000", "localhost", "127.0.0.1:http", "127.0.0.1:70000", "::1:8000"])
def test_a_bad_address_is_refused_with_its_field(address):
    with pytest.raises(ValueError, match="server.http: .*HOST:PORT|server.http: an IPv6 host"):
        split_address(address)
    with pytest.raises(ConfigError, match="server.http"):
        load_config(None, {"server": {"http": address}})


@pytest.mark.parametrize(
    "host, loopback",
    [
        ("127.0.0.1", True),
        ("127.3.2.1", True),
        ("::1", True),
        ("::ffff:127.0.0.1", True),
        ("localhost", True),
        ("LocalHost.", True),
        ("0.0.0.0", False),
        ("::", False),
        ("192.168.1.20", False),
        ("fe80::1", False),
        ("map.example", False),  # not resolved: it counts as reachable
        ("localhost.example", False),
    ],
)
def test_what_counts_as_loopback(host, loopback):
    assert is_loopback(host) is loopback


@pytest.mark.parametrize("http", ["0.0.0.0:8000", "[::]:8000", "192.168.1.20:8000", "map.example:8000"])
def test_beyond_loopback_the_server_needs_tls_and_tokens_or_says_insecure(http):
    with pytest.raises(ValueError, match="without TLS and tokens") as error:
        ServerConfig(http=http).check_http()
    for flag in ("--http-tls-cert", "--http-tls-key", "--http-tokens", "--http-insecure"):
        assert flag in str(error.value)
    with pytest.raises(ValueError, match="without TLS: .*in the clear"):
        ServerConfig(http=http, http_tokens="t").check_http()
    with pytest.raises(ValueError, match="without tokens: .* anyone who reaches it reads the whole map"):
        ServerConfig(http=http, http_tls_cert="c", http_tls_key="k").check_http()
    secure = ServerConfig(http=http, **SECURE)
    secure.check_http()
    assert secure.http_exposure() is None
    insecure = ServerConfig(http=http, http_insecure=True)
    insecure.check_http()
    assert "--http-insecure: serving" in insecure.http_exposure()


@pytest.mark.parametrize("http", ["127.0.0.1:8000", "localhost:8000", "[::1]:8000", ":8000", ""])
def test_loopback_stays_open_without_tls_and_tokens(http):
    config = ServerConfig(http=http)
    config.check_http()
    assert config.http_exposure() is None


def test_settings_that_go_together():
    with pytest.raises(ValueError, match="give both --http-tls-cert and --http-tls-key"):
        ServerConfig(http_tls_cert="c").check_http()
    with pytest.raises(ValueError, match="give both"):
        ServerConfig(http_tls_key="k").check_http()
    with pytest.raises(ValueError, match="the HTTP API is off"):
        ServerConfig(http="", http_tokens="t").check_http()


def test_a_file_and_the_flags_together_decide(tmp_path):
    """The file binds 0.0.0.0 and names the certificate; the flags add the key and the tokens."""
    path = tmp_path / "server.toml"
    path.write_text('[server]\nhttp = "0.0.0.0:8443"\nhttp_tls_cert = "cert.pem"\n')
    config = resolved("--config", str(path), "--http-tls-key", "key.pem", "--http-tokens", "t.txt")
    config.check_http()
    assert (config.http, config.http_tls_cert, config.http_tls_key, config.http_tokens) == (
        "0.0.0.0:8443",
        "cert.pem",
        "key.pem",
        "t.txt",
    )
    assert resolved("--http", "0.0.0.0:1", "--http-insecure").http_insecure
    assert not resolved().http_insecure and resolved().http == "127.0.0.1:8000"
