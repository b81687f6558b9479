"""Where the repository and the real data are."""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]  # the repository
DATA = ROOT.parent / "shared" / "data"  # the real data, beside the repository as ../shared/data
