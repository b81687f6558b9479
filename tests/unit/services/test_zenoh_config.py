"""Zenoh endpoints and config files: refused at the boundary with the field, not by a Zenoh traceback."""

from __future__ import annotations

import re

import pytest

from services import cli
from services.config import ConfigError, load_config
from services.zenoh_config import DEFAULT_ENDPOINT, check_endpoints, zenoh_config


@pytest.mark.parametrize(
    "endpoint",
    [
        DEFAULT_ENDPOINT,
        "tcp/0.0.0.0:7447",
        "tcp/router:7447",  # a name is not resolved: the router may not be up yet
        "tcp/[::1]:0",
        "udp/127.0.0.1:7447?iface=lo",
        "tls/127.0.0.1:7447#root_ca_certificate=ca.pem",
        "unixsock-stream//tmp/gmmap.sock",
    ],
)
def test_endpoints_zenoh_can_use_are_accepted(endpoint):
    check_endpoints("agent.zenoh_connect", [endpoint])
    zenoh_config("peer", listen=[endpoint])


@pytest.mark.parametrize(
    "endpoint",
    [
        "notanendpoint",
        "",
        "tcp/localhost",  # Zenoh's parser takes these three; a client retries them forever
        "foo/127.0.0.1:7447",
        "tcp/host:http",
        "TCP/127.0.0.1:7447",
        "tcp/:7447",
        "tcp/::1:7447",
        "tcp/127.0.0.1:70000",
        "unixsock-stream/",
        "tcp/127.0.0.1:7447#a=b?c=d",  # the ?metadata comes before the #config
    ],
)
def test_a_bad_endpoint_is_refused_naming_its_field(endpoint):
    refusal = f"^agent.zenoh_connect: must be PROTO/HOST:PORT .*, got {re.escape(repr(endpoint))}$"
    with pytest.raises(ValueError, match=refusal):
        check_endpoints("agent.zenoh_connect", [endpoint])
    with pytest.raises(ConfigError, match="^agent.zenoh_connect: "):
        load_config(overrides={"agent": {"zenoh_connect": [DEFAULT_ENDPOINT, endpoint]}})
    for side in ("listen", "connect"):
        with pytest.raises(ValueError, match=f"^Zenoh {side} endpoint: "):
            zenoh_config("peer", **{side: [endpoint]})


def test_a_bad_zenoh_config_file_is_refused_with_its_path(tmp_path):
    broken = tmp_path / "broken.json5"
    broken.write_text("{listen: ")
    for path in (broken, tmp_path / "missing.json5"):
        with pytest.raises(ValueError, match=f"^--zenoh-config: cannot use {path}: ") as refused:
            zenoh_config("peer", config_file=str(path))
        assert ".rs:" not in str(refused.value)  # not the Rust source location Zenoh appends


def test_the_command_line_refuses_a_bad_endpoint_with_exit_2(capsys):
    assert cli.main(["router", "--listen", "x"]) == 2
    assert "gmmap router: Zenoh listen endpoint: must be PROTO/HOST:PORT" in capsys.readouterr().err
    assert cli.main(["agent", "--robot", "a", "--source", "x", "--zenoh-connect", "bogus"]) == 2
    assert "gmmap agent: agent.zenoh_connect: must be PROTO/HOST:PORT" in capsys.readouterr().err
