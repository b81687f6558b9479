"""The names of the simulated worlds, for argument parsers: importing this costs nothing, where
services.sim.worlds compiles its numba kernels. tests/unit/services/sim/test_world_names.py keeps
it equal to the keys of worlds.WORLDS."""

WORLD_NAMES = ("mine", "office", "warehouse")  # sorted
