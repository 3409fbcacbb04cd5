"""Fixtures of the mocap importer tests: tiny synthetic files in the real AMASS / BVH formats."""

import pytest
from tests.helpers.mocap_files import write_amass, write_bvh


@pytest.fixture()
def bvh_writer():
    return write_bvh


@pytest.fixture()
def amass_writer():
    return write_amass
