"""Reading OctoMap trees in tests (octomap-python, in the [bench] and [dev] extras)."""

from __future__ import annotations


def node_log_odds(tree, point) -> float | None:
    """The log-odds of `tree`'s node at `point`; None where it has none (unknown)."""
    import octomap

    try:
        return tree.search(point).getLogOdds()
    except octomap.NullPointerException:
        return None
