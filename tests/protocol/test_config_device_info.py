"""protocol.config: the §5 device-info register table and the APS time writes."""

import dataclasses

import pytest

from davis_rig.errors import ProtocolError
from davis_rig.protocol.config import (
    DEVICE_INFO_REGISTERS,
    MAX_EXPOSURE_US,
    MAX_FRAME_INTERVAL_US,
    Aps,
    Clocks,
    ConfigWrite,
    DeviceFeatures,
    Module,
    device_info_fields,
    exposure_write,
    frame_interval_write,
)
from davis_rig.protocol.layout import SensorLayout

#: PROTOCOL.md §5 steps 2-3: the read-only registers in libcaer's read order, (module, param).
WIRE_ORDER = [(6, 1), (6, 2), (1, 10), (1, 30), (1, 40), (1, 50), (1, 60), (1, 80), (2, 3), (2, 6), (4, 10), (0, 80),
              (1, 0), (1, 1), (1, 2), (2, 0), (2, 1), (2, 2), (3, 0), (6, 3), (6, 4), (6, 5), (6, 6), (3, 1)]


def test_registers_in_wire_order_each_once():
    assert [(int(m), int(p)) for m, p, _ in DEVICE_INFO_REGISTERS] == WIRE_ORDER
    fields = [f for _, _, f in DEVICE_INFO_REGISTERS]
    assert len(set(fields)) == len(fields)


def test_register_fields_cover_layout_clocks_and_features_exactly():
    values = {field: 0 for _, _, field in DEVICE_INFO_REGISTERS}
    assert set(device_info_fields(values, "layout")) == {f.name for f in dataclasses.fields(SensorLayout)}
    assert set(device_info_fields(values, "clocks")) == {f.name for f in dataclasses.fields(Clocks)}
    assert set(device_info_fields(values, "features")) == {f.name for f in dataclasses.fields(DeviceFeatures)}
    assert set(values) - {f for f in values if "." in f} == {"is_master"}


def test_device_info_fields_strips_the_group_prefix():
    values = {"clocks.adc_mhz": 30, "layout.chip_id": 5, "is_master": 1, "clocks.deviation": 1000}
    assert device_info_fields(values, "clocks") == {"adc_mhz": 30, "deviation": 1000}
    assert device_info_fields(values, "features") == {}


def test_aps_time_writes_in_adc_cycles_and_range_checked():
    clocks = Clocks(logic_mhz=104, adc_mhz=30, usb_mhz=80, deviation=1000)
    assert exposure_write(4000, clocks) == ConfigWrite(Module.APS, Aps.EXPOSURE, 120_000)
    assert frame_interval_write(40_000, clocks) == ConfigWrite(Module.APS, Aps.FRAME_INTERVAL, 1_200_000)
    with pytest.raises(ProtocolError, match=f"exposure must be 0..{MAX_EXPOSURE_US} µs, got -1"):
        exposure_write(-1, clocks)
    with pytest.raises(ProtocolError, match=f"frame interval must be 0..{MAX_FRAME_INTERVAL_US} µs"):
        frame_interval_write(MAX_FRAME_INTERVAL_US + 1, clocks)
