"""An HTTP client of a map server's API (the sim's and the demo's): a bearer token and the CA to
trust, both read from files, so neither appears on a command line."""

from __future__ import annotations

import functools
import http.client
import io
import ssl
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from email.message import Message
from pathlib import Path

from services.map_server.config import ServerConfig, split_address


def read_token(path: str | Path) -> str:
    """The one word of a token file (what `gmmap token` printed); ValueError naming the file."""
    try:
        words = Path(path).read_text(encoding="utf-8").split()
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"--http-token: cannot read {path}: {getattr(error, 'strerror', None) or error}") from None
    if len(words) != 1:
        raise ValueError(f"--http-token: {path} must hold the token alone, got {len(words)} words")
    return words[0]


@functools.lru_cache(maxsize=8)
def tls_context(ca_file: str | None) -> ssl.SSLContext:
    """Verifies the server's certificate and name against `ca_file` (None: the system's CAs)."""
    try:
        return ssl.create_default_context(cafile=ca_file)
    except (OSError, ssl.SSLError) as error:
        raise ValueError(f"--http-ca: {ca_file} is not a PEM CA bundle ({error})") from None


@dataclass(frozen=True)
class HttpClient:
    """GETs under `base` (http://HOST:PORT or https://...). Plain values: it pickles into the processes
    of the sim's tile clients."""

    base: str
    token: str | None = None
    ca_file: str | None = None

    @classmethod
    def for_server(cls, server: ServerConfig, token_file: str | None, ca_file: str | None) -> HttpClient:
        """A client of `server` on this machine, at 127.0.0.1 when it binds every address."""
        host, port = split_address(server.http)
        host = {"0.0.0.0": "127.0.0.1", "::": "::1"}.get(host, host)
        host = f"[{host}]" if ":" in host else host
        if server.http_tokens and not token_file:
            raise ValueError("--http-token: the server has tokens (--http-tokens): give a file holding one of them")
        token = read_token(token_file) if token_file else None
        if ca_file:
            tls_context(ca_file)  # a bad CA file is said now, not at the first request
        return cls(f"{'https' if server.http_tls else 'http'}://{host}:{port}", token, ca_file)

    def get(self, path: str, timeout: float) -> bytes:
        """The body of GET `path`; urllib's HTTPError (an OSError) for a 4xx or 5xx, URLError when unreachable."""
        return self.fetch(path, timeout)[0]

    def fetch(self, path: str, timeout: float) -> tuple[bytes, Message]:
        """The body and headers of GET `path`; raises as `get`."""
        headers = {"Authorization": f"Bearer {self.token}"} if self.token else {}
        context = tls_context(self.ca_file) if self.base.startswith("https:") else None
        request = urllib.request.Request(self.base + path, headers=headers)
        with urllib.request.urlopen(request, timeout=timeout, context=context) as response:
            return response.read(), response.headers


class Connection:
    """One persistent HTTP/1.1 connection to an HttpClient's server, as a browser keeps one for a
    viewer: GETs reuse it (urllib opens and closes one per request, which costs the server and the
    client about 0.25 and 0.2 ms more a tile), and it is opened again once the server closed it.
    Errors as HttpClient.fetch: HTTPError (an OSError) for a 4xx or 5xx. One per thread."""

    def __init__(self, client: HttpClient, timeout: float):
        self._client, self._timeout = client, timeout
        self._url = urllib.parse.urlsplit(client.base)
        self._headers = {"Authorization": f"Bearer {client.token}"} if client.token else {}
        self._open: http.client.HTTPConnection | None = None

    def fetch(self, path: str) -> tuple[bytes, Message]:
        """The body and headers of GET `path`."""
        retried = False
        while True:
            if self._open is None:
                self._open = self._connect()
            try:
                self._open.request("GET", path, headers=self._headers)
                response = self._open.getresponse()
                body = response.read()
            except (http.client.RemoteDisconnected, ConnectionResetError, BrokenPipeError):
                self.close()  # closed by the server while idle: a GET may be asked again on a new one
                if retried:
                    raise
                retried = True
                continue
            except BaseException:
                self.close()
                raise
            if response.will_close:
                self.close()
            if response.status >= 400:
                url = self._client.base + path
                raise urllib.error.HTTPError(url, response.status, response.reason, response.headers, io.BytesIO(body))
            return body, response.headers

    def _connect(self) -> http.client.HTTPConnection:
        host, port = self._url.hostname, self._url.port
        if self._url.scheme == "https":
            return http.client.HTTPSConnection(
                host, port, timeout=self._timeout, context=tls_context(self._client.ca_file)
            )
        return http.client.HTTPConnection(host, port, timeout=self._timeout)

    def close(self) -> None:
        if self._open is not None:
            self._open.close()
            self._open = None
