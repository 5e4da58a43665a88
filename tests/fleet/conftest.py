"""Fixtures of the fleet tests."""

import pytest
from fleet_data import MODEL, write_fleet

from thetahat.fleet import estimate_many


@pytest.fixture(scope="session")
def fleet_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleet")
    write_fleet(d)
    return d


@pytest.fixture(scope="session")
def fleet(fleet_dir):
    """The fleet estimated in this process, 8 records per task."""
    return estimate_many(MODEL, fleet_dir, chunk_size=8, progress=False)
