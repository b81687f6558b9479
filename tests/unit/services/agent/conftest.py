"""The agent tests' offline agent."""

from __future__ import annotations

import pytest

from services.agent.agent import Agent
from services.agent.config import AgentConfig
from services.agent.outbox import Outbox
from services.zenoh_config import zenoh_config
from support.net import free_port


@pytest.fixture
def offline_agent(tmp_path):
    """An agent whose server is not there: what it sends stays in its outbox."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    options = AgentConfig(robot="r", zenoh_connect=(endpoint,), pose_tolerance=0.01)
    agent = Agent(options, Outbox(tmp_path / "o.db", "default", "r"), zenoh_config("client", connect=[endpoint]))
    yield agent
    agent.close()
    agent.outbox.close()
