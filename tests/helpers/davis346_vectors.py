"""Test helper: the committed DAVIS346 test vectors and the one full comparison of a decode with a vector.

Used by the decoder tests
(``tests/protocol``) and by the camera tests that decode the same vectors through the real pyusb path
(``tests/device``), so both compare events, special events, frames (pixels, every timestamp, position) and IMU
samples the same way.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from davis_rig.protocol import IMU6_DTYPE, SPECIAL_DTYPE, DecodedChunk, SensorLayout, SpecialType
from davis_rig.types import EVENT_DTYPE

#: The committed copy of ``shared/davis346/test_vectors.json``.
VECTORS_PATH = Path(__file__).resolve().parents[1] / "fixtures" / "davis346_test_vectors.json"
#: Every vector (dicts with ``id``, ``device_info``, ``transfers_hex``, ``expected``, ...).
VECTORS: list[dict] = json.loads(VECTORS_PATH.read_text())["vectors"]
#: The vectors' ids, for ``pytest.mark.parametrize(..., ids=VECTOR_IDS)``.
VECTOR_IDS: list[str] = [v["id"] for v in VECTORS]

#: libcaer's marker for "time not representable" in a vector's special events (INT32_MAX).
_INT32_MAX = 2**31 - 1


def vector_layout(vector: dict) -> SensorLayout:
    """The sensor layout of a vector's ``device_info`` read-outs."""
    return SensorLayout.from_mapping(vector["device_info"])


def vector_transfers(vector: dict) -> list[bytes]:
    """A vector's USB transfers as bytes, in order (empty transfers kept)."""
    return [bytes.fromhex(t) for t in vector["transfers_hex"]]


def events_as_lists(events: np.ndarray) -> list[list[int]]:
    """Events [N] of ``EVENT_DTYPE`` as ``[[t_us, x, y, p], ...]`` (the vectors' ``dvs`` form)."""
    return [[int(e["t"]), int(e["x"]), int(e["y"]), int(e["p"])] for e in events]


def assert_matches_expected(chunk: DecodedChunk, expected: dict) -> None:
    """Compare a decoded chunk with a vector's ``expected`` block (our documented marker convention).

    Checks DVS events (t µs, x, y, p), special events (type and t µs; a reset is reported at t = 0 and a big
    wrap at the new wrap base, where libcaer writes INT32_MAX), APS frames (four timestamps µs, libcaer's
    mid-exposure timestamp, position, shape, 16-bit and 10-bit pixels) and IMU samples (t µs; g, °/s, °C
    within the vector's tolerance, default 1e-4).

    Raises:
        AssertionError: the first difference.
    """
    assert chunk.events.dtype == EVENT_DTYPE
    assert events_as_lists(chunk.events) == expected["dvs"]

    assert chunk.specials.dtype == SPECIAL_DTYPE
    got_types = [int(s["type"]) for s in chunk.specials]
    assert got_types == [s["libcaer_type_id"] for s in expected["special"]]
    for got, exp in zip(chunk.specials, expected["special"]):
        if exp["t_us"] == _INT32_MAX and exp["libcaer_type_id"] == SpecialType.TIMESTAMP_RESET:
            assert int(got["t"]) == 0  # our convention: time right after the reset
        elif exp["t_us"] == _INT32_MAX and exp["libcaer_type_id"] == SpecialType.TIMESTAMP_WRAP:
            # our convention: the new wrap base right after the big wrap (a multiple of 2**15, >= 2**31)
            assert int(got["t"]) % 2**15 == 0 and int(got["t"]) >= 2**31
        else:
            assert int(got["t"]) == exp["t_us"]

    assert len(chunk.frames) == len(expected["frames"])
    for frame, exp in zip(chunk.frames, expected["frames"]):
        assert frame.t_start_of_frame_us == exp["ts_start_of_frame"]
        assert frame.t_start_exposure_us == exp["ts_start_of_exposure"]
        assert frame.t_end_exposure_us == exp["ts_end_of_exposure"]
        assert frame.t_end_of_frame_us == exp["ts_end_of_frame"]
        assert frame.t_exposure_mid_us == exp["libcaer_frame_timestamp"]
        assert (frame.position_x, frame.position_y) == (exp["position_x"], exp["position_y"])
        assert frame.pixels.shape == (exp["length_y"], exp["length_x"])
        assert frame.pixels.dtype == np.uint16
        assert frame.pixels.ravel().tolist() == exp["pixels_row_major"]
        assert frame.pixels_10bit.ravel().tolist() == exp["pixels_10bit"]

    assert chunk.imu.dtype == IMU6_DTYPE
    assert len(chunk.imu) == len(expected["imu6"])
    for sample, exp in zip(chunk.imu, expected["imu6"]):
        assert int(sample["t"]) == exp["t_us"]
        tol = exp.get("tolerance", 1e-4)
        got_accel = [sample["accel_x_g"], sample["accel_y_g"], sample["accel_z_g"]]
        got_gyro = [sample["gyro_x_dps"], sample["gyro_y_dps"], sample["gyro_z_dps"]]
        np.testing.assert_allclose(got_accel, exp["accel_g"], atol=tol)
        np.testing.assert_allclose(got_gyro, exp["gyro_dps"], atol=tol)
        assert abs(float(sample["temperature_c"]) - exp["temp_c"]) <= tol
