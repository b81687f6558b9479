from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not DATA.is_dir():
        pytest.skip(f"real data folder {DATA} is absent (it sits beside the repository as ../shared/data)")
    return DATA


@pytest.fixture(scope="session")
def intel_scans(data_dir):
    from services.datasets import read_scans

    return list(read_scans(data_dir / "carmen" / "intel-corrected.log.gz"))
