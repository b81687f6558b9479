"""A real uvicorn server for an app, in a background thread of the test process."""

from __future__ import annotations

import socket
import threading
import time

import uvicorn

from services.api.limits import MAX_REQUEST_HEAD, JsonErrorH11


class Server:
    """A uvicorn server for `app` in a background thread, on a free port of 127.0.0.1; HTTPS when given
    a certificate and its key (PEM files)."""

    def __init__(self, app, tls_cert: str | None = None, tls_key: str | None = None):
        self.socket = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.socket.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.socket.bind(("127.0.0.1", 0))
        self.port = self.socket.getsockname()[1]
        self.url = f"{'https' if tls_cert else 'http'}://127.0.0.1:{self.port}"
        # h11's request-head limit and protocol as gmmap's server sets them: with h11's default
        # (16 KiB), a long GET parsed only when it came in one piece, and got a plain 400 when the
        # host split it (test_bad_points' 10,001 points, in a fresh-clone run on a loaded 2-core EPYC).
        config = uvicorn.Config(
            app,
            log_level="warning",
            lifespan="off",
            http=JsonErrorH11,
            h11_max_incomplete_event_size=MAX_REQUEST_HEAD,
            ssl_certfile=tls_cert,
            ssl_keyfile=tls_key,
        )
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.socket]}, daemon=True)

    def __enter__(self):
        self.thread.start()
        deadline = time.monotonic() + 20
        while not self.server.started:
            assert self.thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
            time.sleep(0.02)
        return self

    def __exit__(self, *exc):
        self.server.should_exit = True
        self.thread.join(timeout=10)
        self.socket.close()
