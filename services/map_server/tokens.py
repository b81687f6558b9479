"""Bearer tokens of the HTTP API: the `--http-tokens` file, and new tokens (`gmmap token NAME`).

The file holds one client a line, `NAME sha256:HEX [robots=ID,ID,...]`, and `#` comments:

    # who        sha256 of the token                                                  what it reads
    control-room sha256:7b351761ee3cdbc8b8853a8c5b094c0787a5e75d68f81b8aac81263e16f5e8c6
    dock-west    sha256:08adc5cb2eca8e757f32531630bfc24a322458666ad5c603bce7fee5ec57ffc0 robots=a,b

Only the SHA-256 of each token is kept: the file gives nothing away if read. A slow password hash
(bcrypt, scrypt, Argon2) buys nothing here: it slows guessing a low-entropy password from its hash,
and a token is 256 random bits (`secrets.token_urlsafe(32)`), which no one can guess from a fast hash
either; a slow hash would cost every request (every map tile) tens of milliseconds instead.

No web framework is imported here: `gmmap token` runs without loading the API.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import os
import re
import secrets
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from protocol import ProtocolError, check_id

log = logging.getLogger("gmmap.http")

PREFIX = "gmmap_"  # on every token: secret scanners and people can tell one when they see it
DIGEST = re.compile(r"sha256:([0-9a-f]{64})")
RELOAD_S = 1.0  # at most this often the file's stat is read, to pick up added or revoked clients


@dataclass(frozen=True)
class Client:
    """One line of the file: who, the SHA-256 of their token, and the robots they may read (None: all)."""

    name: str
    digest: bytes
    robots: frozenset[str] | None = None

    def line(self) -> str:
        robots = f" robots={','.join(sorted(self.robots))}" if self.robots is not None else ""
        return f"{self.name} sha256:{self.digest.hex()}{robots}"


def digest(token: str) -> bytes:
    return hashlib.sha256(token.encode("utf-8")).digest()


def new_token(name: str, robots: list[str] | None = None) -> tuple[str, Client]:
    """A fresh token (256 random bits) and its client line."""
    token = PREFIX + secrets.token_urlsafe(32)
    return token, Client(check_id(name, "name"), digest(token), None if robots is None else frozenset(robots))


def parse_tokens(text: str, path: str) -> list[Client]:
    """The clients of a token file's text; ValueError naming `path` and the line."""
    clients: dict[str, Client] = {}
    digests: dict[bytes, str] = {}
    for number, raw in enumerate(text.splitlines(), 1):
        words = raw.split("#", 1)[0].split()
        if not words:
            continue
        where = f"{path} line {number}"
        if len(words) not in (2, 3):
            raise ValueError(f"{where}: expected NAME sha256:HEX [robots=ID,...], got {len(words)} words")
        name, hashed, *rest = words
        try:
            check_id(name, "name")
        except ProtocolError as error:
            raise ValueError(f"{where}: {error}") from None
        match = DIGEST.fullmatch(hashed)
        if match is None:
            raise ValueError(f"{where}: the second word must be sha256: and 64 hex digits (not the token itself)")
        robots = None
        if rest:
            if not rest[0].startswith("robots="):
                raise ValueError(f"{where}: the third word must be robots=ID,ID,..., got {rest[0]!r:.40}")
            try:
                robots = frozenset(check_id(r, "robots") for r in rest[0][len("robots=") :].split(","))
            except ProtocolError as error:
                raise ValueError(f"{where}: {error}") from None
        if name in clients:
            raise ValueError(f"{where}: client {name} is already on an earlier line")
        value = bytes.fromhex(match.group(1))
        if value in digests:
            raise ValueError(f"{where}: the same token as client {digests[value]}: give each client its own")
        clients[name], digests[value] = Client(name, value, robots), name
    return list(clients.values())


def read_tokens(path: str | Path) -> list[Client]:
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"--http-tokens: cannot read {path}: {getattr(error, 'strerror', None) or error}") from None
    return parse_tokens(text, str(path))


class TokenFile:
    """The clients of a token file, read again when it changes (within RELOAD_S), so that adding or
    revoking a client needs no restart. A file that no longer reads or parses keeps the clients it had
    (an editor may replace the file in two steps); the error is logged."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._stamp = self._stat()
        self._clients = read_tokens(self.path)
        self._checked = time.monotonic()

    def _stat(self) -> tuple[int, int, int] | None:
        try:
            s = os.stat(self.path)
        except OSError:
            return None
        return s.st_mtime_ns, s.st_size, s.st_ino

    @property
    def clients(self) -> list[Client]:
        now = time.monotonic()
        if now - self._checked >= RELOAD_S:
            self._checked = now
            stamp = self._stat()
            if stamp != self._stamp:
                try:
                    self._clients = read_tokens(self.path)
                    self._stamp = stamp
                    log.warning("HTTP tokens: %d clients from %s", len(self._clients), self.path)
                except ValueError as error:
                    log.error("HTTP tokens: keeping the %d clients read before: %s", len(self._clients), error)
        return self._clients

    def client(self, token: str) -> Client | None:
        """The client whose token this is, or None. Every digest is compared, each in constant time."""
        presented = digest(token)
        found = None
        for client in self.clients:
            if hmac.compare_digest(client.digest, presented):
                found = client
        return found


def run_token(name: str, robots: list[str] | None, add: str | None) -> int:
    """`gmmap token`: print a new token on stdout, and its line for the token file (or append it to `add`)."""
    token, client = new_token(name, robots)
    if add:
        path = Path(add)
        if any(c.name == client.name for c in (read_tokens(path) if path.exists() else [])):
            raise ValueError(f"{path}: client {client.name} already has a token; remove its line first")
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)  # a new file: readable by its owner only
        with os.fdopen(fd, "a", encoding="utf-8") as f:
            f.write(client.line() + "\n")
        print(f"added {client.name} to {path}", file=sys.stderr)
    else:
        print(f"add this line to the --http-tokens file:\n{client.line()}", file=sys.stderr)
    print(token)
    return 0
