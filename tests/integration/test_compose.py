"""docker-compose.yml and the Dockerfile: the file validates, and every command is a real `gmmap` command line."""

from __future__ import annotations

import shutil
import subprocess

import pytest
import yaml

from services.cli import build_parser
from services.cli_flags import resolve_config
from services.sim.fleet import SimSource
from support.paths import ROOT

COMPOSE = ROOT / "docker-compose.yml"


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def gmmap_services(compose: dict) -> dict:
    return {name: s for name, s in compose["services"].items() if s.get("image", "").startswith("gmmap")}


def compose_command() -> list[str] | None:
    """Debian's `docker-compose` (works offline), else the `docker compose` plugin, else None."""
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    plugin = ["docker", "compose"]
    if shutil.which("docker") and subprocess.run([*plugin, "version"], capture_output=True).returncode == 0:
        return plugin
    return None


def test_compose_file_validates():
    command = compose_command()
    if command is None:
        pytest.skip("no compose parser: install Debian's docker-compose (make test does so as root)")
    result = subprocess.run(
        [*command, "-f", str(COMPOSE), "config", "-q"], capture_output=True, text=True, cwd=ROOT, timeout=60
    )
    assert result.returncode == 0, result.stderr


def test_router_server_and_three_simulated_robots(compose):
    services = compose["services"]
    assert services["router"]["image"].startswith("eclipse/zenoh:")
    assert "--no-multicast-scouting" in services["router"]["command"]
    ours = gmmap_services(compose)
    assert all(s["build"] == "." for s in ours.values())
    commands = {name: s["command"] for name, s in ours.items()}
    assert sorted(c[0] for c in commands.values()) == ["agent", "agent", "agent", "server"]
    assert all("router" in s.get("depends_on", []) for s in ours.values())


def test_every_command_parses_as_gmmap(compose):
    parser = build_parser()
    robots, sources = [], []
    for name, service in gmmap_services(compose).items():
        args = parser.parse_args(service["command"])
        config = resolve_config(args)
        if args.command == "server":
            server = config.server
            assert server.zenoh_connect == ("tcp/router:7447",) and server.listen == (), name
            host, port = server.http.split(":")
            assert host == "0.0.0.0" and service["ports"] == [f"127.0.0.1:8000:{port}"]
            # Published on the host's loopback only, so served without TLS or tokens: explicitly, as it must be.
            assert server.http_insecure and not (server.http_tls or server.http_tokens)
            server.check_http()
            assert server.data_dir in [v.split(":")[1] for v in service["volumes"]]
        else:
            agent = config.agent
            assert agent.zenoh_connect == ("tcp/router:7447",), name
            sim = SimSource.parse(agent.source)
            assert agent.scans.startswith("0:") and int(agent.scans[2:]) > 0 and agent.rate > 0
            assert agent.outbox.startswith(service["volumes"][0].split(":")[1])  # the outbox survives restarts
            robots.append(agent.robot)
            sources.append(sim)
    assert len(set(robots)) == 3
    assert sorted(s.index for s in sources) == [0, 1, 2] and {(s.world, s.robots, s.seed) for s in sources} == {
        ("office", 3, 0)
    }


def test_dockerfile_installs_the_package_on_python_311_slim():
    lines = [
        line.strip()
        for line in (ROOT / "Dockerfile").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    assert lines[0] == "FROM python:3.11-slim"
    assert any(line.startswith("RUN pip install") and " ." in line for line in lines)
    assert 'ENTRYPOINT ["gmmap"]' in lines
    for copied in (line.split()[1] for line in lines if line.startswith("COPY")):
        assert (ROOT / copied).exists(), copied
