"""The loopback ports handed to a simulation's children (services.sim.processes.free_port)."""

import socket

from services.sim import processes


class ScriptedSocket:
    """A socket whose bind to port 0 gets the next port of `ports`, as the kernel may reuse one."""

    ports: list[int] = []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def bind(self, address):
        assert address == ("127.0.0.1", 0)

    def getsockname(self):
        return ("127.0.0.1", self.ports.pop(0))


def test_free_port_never_hands_out_a_port_twice(monkeypatch):
    # The first port is released at once, so the kernel may give it again to the next bind: a
    # server's Zenoh and HTTP ports were once the same ("address already in use").
    monkeypatch.setattr(processes, "_handed_out", set())
    monkeypatch.setattr(ScriptedSocket, "ports", [40001, 40001, 40001, 40002])
    monkeypatch.setattr(socket, "socket", ScriptedSocket)
    assert processes.free_port() == 40001
    assert processes.free_port() == 40002


def test_free_port_is_free_on_loopback():
    port = processes.free_port()
    with socket.socket() as s:
        s.bind(("127.0.0.1", port))  # nothing holds it
