"""Loopback ports, polling, and reading a server's HTTP answers."""

from __future__ import annotations

import json
import time
import urllib.error
import urllib.request

from services.sim.processes import free_port as free_port  # the repository's one, re-exported


def wait_for(condition, timeout: float, what: str, interval: float = 0.05):
    """The first truthy value of `condition()`, polled every `interval` s for at most `timeout` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(interval)


def http_get(port: int, path: str) -> bytes:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=30) as response:
        return response.read()


def get(url: str):
    """(status, headers, body) of a GET, 4xx and 5xx included."""
    try:
        with urllib.request.urlopen(url, timeout=60) as reply:
            return reply.status, reply.headers, reply.read()
    except urllib.error.HTTPError as e:
        return e.code, e.headers, e.read()


def post(url: str, payload) -> tuple[int, bytes]:
    """(status, body) of a JSON POST, 4xx and 5xx included."""
    return post_bytes(url, json.dumps(payload).encode())


def post_bytes(url: str, body: bytes) -> tuple[int, bytes]:
    """(status, body) of a POST of `body` as application/json, whatever it holds; 4xx and 5xx included."""
    request = urllib.request.Request(url, body, {"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(request, timeout=60) as reply:
            return reply.status, reply.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


def metric(text: str, name: str, **labels) -> float:
    """Sum of a Prometheus sample over the series whose labels include `labels`."""
    total = 0.0
    for line in text.splitlines():
        if line.startswith(name + "{") or line.startswith(name + " "):
            series, value = line.rsplit(" ", 1)
            if all(f'{k}="{v}"' in series for k, v in labels.items()):
                total += float(value)
    return total
