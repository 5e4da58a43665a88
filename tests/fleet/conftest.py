"""Fixtures of the fleet tests."""

import pytest
from fleet_data import write_fleet


@pytest.fixture(scope="session")
def fleet_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleet")
    write_fleet(d)
    return d
