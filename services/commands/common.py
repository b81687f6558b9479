"""What several commands run with, beyond their flags: logging to stderr, and a log's scans read with
progress bars."""

from __future__ import annotations

import sys

from services.cli_flags import source_options
from services.config import GmmapConfig


def log_to_stderr(verbose: bool) -> None:
    import logging

    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        stream=sys.stderr,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
    )


def progress_bars():
    from tqdm import tqdm

    bars = []

    def start(stage: str, total: int):
        bar = tqdm(total=total, desc=stage, unit="scan", file=sys.stderr, leave=False)
        bars.append(bar)
        return bar.update

    return start, bars


def read_source(args, config: GmmapConfig, keep_fraction: float = 1.0, seed: int = 0, **options) -> tuple[list, int]:
    """The scans of the source that the keyframe policy keeps, and how many were read."""
    from tqdm import tqdm

    from services.datasets import count_scans, read_scans
    from services.datasets.keyframes import keyframes

    options |= source_options(args)
    total = count_scans(args.log, args.format, **options)
    scans = read_scans(args.log, args.format, keep_fraction=keep_fraction, seed=seed, **options)
    with tqdm(scans, total=total, desc="read", unit="scan", file=sys.stderr, leave=False) as bar:
        kept = list(keyframes(bar, config.keyframe, lambda s: (s.pose, s.stamp)))
        return kept, bar.n
