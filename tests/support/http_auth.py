"""What a server with TLS and tokens needs in a test: trial certificates (docs/security/make-certs.sh,
which runs openssl) and a token file with its tokens."""

from __future__ import annotations

import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

from services.map_server.tokens import new_token
from support.paths import ROOT


@dataclass(frozen=True)
class Certs:
    ca: Path  # the CA that signed `cert`
    cert: Path  # for 127.0.0.1 and localhost
    key: Path


def make_certs(folder: Path) -> Certs:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not on PATH: no trial certificates (apt-get install openssl)")
    script = ROOT / "docs" / "security" / "make-certs.sh"
    subprocess.run(["sh", str(script), str(folder)], check=True, capture_output=True, timeout=60)
    return Certs(folder / "ca.pem", folder / "server.pem", folder / "server.key")


def write_tokens(path: Path, clients: dict[str, list[str] | None]) -> dict[str, str]:
    """A token file of `clients` (name: the robots it may read, None for all); the token of each name."""
    tokens, lines = {}, ["# written by tests/support/http_auth.py"]
    for name, robots in clients.items():
        tokens[name], client = new_token(name, robots)
        lines.append(client.line())
    path.write_text("\n".join(lines) + "\n")
    return tokens
