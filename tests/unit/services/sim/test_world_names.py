"""The light list of world names is the registry's, and importing it pulls in no numba."""

import subprocess
import sys

from services.sim.world_names import WORLD_NAMES
from services.sim.worlds import WORLDS
from support.paths import ROOT


def test_world_names_are_the_registrys_keys_sorted():
    assert WORLD_NAMES == tuple(sorted(WORLDS))


def test_world_names_import_without_numba():
    code = "import sys, services.sim.world_names; sys.exit('numba' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], cwd=ROOT).returncode == 0
