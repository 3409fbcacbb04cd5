"""SensorLayout: raw read-outs and derived orientation/sizes (PROTOCOL.md §5)."""

from __future__ import annotations

import dataclasses

import pytest

from davis_rig.errors import ProtocolError
from davis_rig.protocol import SensorLayout


def test_davis346_defaults():
    layout = SensorLayout.davis346()
    assert (layout.dvs_width, layout.dvs_height, layout.aps_width, layout.aps_height) == (346, 260, 346, 260)
    assert layout.dvs_hw == layout.aps_hw == (260, 346)
    assert not (layout.dvs_invert_xy or layout.aps_invert_xy or layout.aps_flip_x or layout.aps_flip_y)
    assert (layout.chip_id, layout.imu_type) == (5, 1)
    with pytest.raises(dataclasses.FrozenInstanceError):
        layout.chip_id = 4


def test_inverted_layout_from_vector_device_info(vectors):
    v14 = next(v for v in vectors if v["id"].startswith("V14"))
    layout = SensorLayout.from_mapping(v14["device_info"])
    assert layout.aps_invert_xy and layout.aps_flip_x and layout.aps_flip_y
    assert (layout.aps_width, layout.aps_height) == (346, 260)  # raw 260 columns × 346 rows, swapped
    v17 = next(v for v in vectors if v["id"].startswith("V17"))
    layout = SensorLayout.from_mapping(v17["device_info"])
    assert layout.dvs_invert_xy
    assert (layout.dvs_width, layout.dvs_height) == (346, 260)
    assert SensorLayout.from_mapping(layout.to_dict()) == layout


def test_imu_flip_bits():
    layout = dataclasses.replace(SensorLayout.davis346(), imu_orientation_info=0b101)
    assert (layout.imu_flip_x, layout.imu_flip_y, layout.imu_flip_z) == (True, False, True)


def test_validation():
    with pytest.raises(ProtocolError, match="missing keys"):
        SensorLayout.from_mapping({"dvs_size_columns": 346})
    with pytest.raises(ProtocolError, match="dvs_size_rows: expected 1..4096"):
        dataclasses.replace(SensorLayout.davis346(), dvs_size_rows=0)
    with pytest.raises(ProtocolError, match="expected an int"):
        dataclasses.replace(SensorLayout.davis346(), chip_id="five")
