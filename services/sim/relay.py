"""A TCP relay that counts the bytes of one robot's link: Zenoh framing, keep-alives and all."""

from __future__ import annotations

import socket
import threading


class CountingRelay:
    """Listens on a free 127.0.0.1 port and forwards every connection to `target_port`.

    `up` counts the bytes from the robot to the server, `down` those coming back (Acks).
    """

    def __init__(self, target_port: int):
        self.target_port = target_port
        self.up = 0
        self.down = 0
        self._lock = threading.Lock()
        self._sockets: list[socket.socket] = []
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = self._listener.getsockname()[1]
        threading.Thread(target=self._accept, name="gmmap-relay", daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                robot, _ = self._listener.accept()
                server = socket.create_connection(("127.0.0.1", self.target_port))
            except OSError:
                return  # closed
            for s in (robot, server):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # as Zenoh's own sockets
            with self._lock:
                self._sockets += [robot, server]
            threading.Thread(target=self._pipe, args=(robot, server, "up"), daemon=True).start()
            threading.Thread(target=self._pipe, args=(server, robot, "down"), daemon=True).start()

    def _pipe(self, source: socket.socket, sink: socket.socket, direction: str) -> None:
        try:
            while data := source.recv(65536):
                with self._lock:  # counted before it is passed on: whoever has the bytes sees the count
                    setattr(self, direction, getattr(self, direction) + len(data))
                sink.sendall(data)
        except OSError:
            pass
        finally:
            for s in (source, sink):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def close(self) -> None:
        self._listener.close()
        with self._lock:
            for s in self._sockets:
                s.close()
