"""The sim's and the demo's HTTP client: where it connects, and its token and CA files."""

from __future__ import annotations

import threading
import urllib.error
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from services.http_client import Connection, HttpClient, read_token
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


class _Handler(BaseHTTPRequestHandler):
    """HTTP/1.1 with keep-alive: /ok answers, /busy is a 503 with Retry-After, /last closes after
    answering and says so, /drop closes without a word."""

    protocol_version = "HTTP/1.1"
    connections: list[int] = []  # one entry per connection the server accepted

    def setup(self):
        super().setup()
        self.connections.append(1)

    def do_GET(self):
        status, body = {"/busy": (503, b"busy")}.get(
            self.path, (200, f"{self.path} {self.headers['Authorization']}".encode())
        )
        self.send_response(status)
        self.send_header("Content-Length", str(len(body)))
        if status == 503:
            self.send_header("Retry-After", "2")
        if self.path == "/last":
            self.send_header("Connection", "close")
        self.end_headers()
        self.wfile.write(body)
        if self.path == "/drop":
            self.close_connection = True  # closed without saying so, as an idle keep-alive times out

    def log_message(self, *args):
        pass


@pytest.fixture()
def keep_alive_server():
    _Handler.connections = []
    server = ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}", _Handler.connections
    server.shutdown()
    server.server_close()


def test_a_connection_is_kept_for_many_gets_and_opened_again_once_closed(keep_alive_server):
    base, connections = keep_alive_server
    connection = Connection(HttpClient(base, token="gmmap_abc"), timeout=5)
    bodies = [connection.fetch(f"/ok{i}")[0] for i in range(5)]
    assert bodies == [f"/ok{i} Bearer gmmap_abc".encode() for i in range(5)]
    assert len(connections) == 1
    with pytest.raises(urllib.error.HTTPError) as shed:  # as urllib: an OSError with the reply's headers
        connection.fetch("/busy")
    assert shed.value.code == 503 and shed.value.headers["Retry-After"] == "2"
    assert connection.fetch("/last")[0].startswith(b"/last")  # the server closes it after this reply ...
    assert connection.fetch("/ok")[0].startswith(b"/ok")  # ... and the next GET opens another
    assert len(connections) == 2
    connection.fetch("/drop")
    assert connection.fetch("/ok")[0].startswith(b"/ok")  # the GET asked again on a new connection
    assert len(connections) == 3
    connection.close()
