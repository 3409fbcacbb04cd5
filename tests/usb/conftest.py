"""Shared helpers for the USB tests: the DAVIS346 test vectors and virtual cameras."""

import json
from pathlib import Path

import pytest

from davis_rig.usb.sources import TransferListSource
from davis_rig.usb.virtual import VirtualDavis346, VirtualDavis346Backend

VECTORS_PATH = Path(__file__).resolve().parents[1] / "fixtures" / "davis346_test_vectors.json"
VECTORS = json.loads(VECTORS_PATH.read_text())["vectors"]


@pytest.fixture
def make_backend():
    """``make_backend(**device_kwargs) -> (backend, device)`` with one virtual DAVIS346."""

    def make(**kwargs):
        device = VirtualDavis346(**kwargs)
        return VirtualDavis346Backend(device), device

    return make


def vector_device(vector, **kwargs) -> VirtualDavis346:
    """A virtual camera reporting a vector's device_info and serving its transfers exactly."""
    return VirtualDavis346(layout=vector["device_info"], source=TransferListSource.from_hex(vector["transfers_hex"]), **kwargs)
