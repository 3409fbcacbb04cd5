"""Shared fixtures of the scene tests: the bundled body asset and body models (loaded once)."""

import pytest

from davis_rig.scene.body import BodyAsset


@pytest.fixture(scope="session")
def asset():
    return BodyAsset.load()


@pytest.fixture(scope="session")
def model(asset):
    from davis_rig.scene.body import BodyModel

    return BodyModel(asset)


@pytest.fixture(scope="session")
def model64(asset):
    import torch

    from davis_rig.scene.body import BodyModel

    return BodyModel(asset, dtype=torch.float64)
