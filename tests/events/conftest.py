"""Fixtures for the event-kernel tests: reference event windows and histograms from the official RVT code.

``reference_windows`` is parametrized over the in-repo mini fixture and the RVT-T fixture in the
``shared/rvt/`` folder beside the repository root (that case is skipped, with the reason, when absent).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
MINI_PATH = REPO_ROOT / "tests" / "fixtures" / "rvt_mini_fixture.safetensors"
RVT_T_PATH = (REPO_ROOT / ".." / "shared" / "rvt" / "rvt_t_fixture.safetensors").resolve()

_INPUT_KEYS = (
    "input.events_x",
    "input.events_y",
    "input.events_t_us",
    "input.events_p",
    "input.window_end_ts_us",
    "input.hist_uint8_unpadded",
)


def _load_inputs(path: Path) -> dict[str, np.ndarray]:
    from safetensors import safe_open

    with safe_open(str(path), framework="np") as handle:
        return {key.split(".", 1)[1]: handle.get_tensor(key) for key in _INPUT_KEYS}


@pytest.fixture(scope="session", params=["mini", "rvt_t"])
def reference_windows(request) -> dict[str, np.ndarray]:
    """Raw events, window ends and the official uint8 histograms of one reference fixture.

    Keys: ``events_x``, ``events_y`` (int16 [N]), ``events_t_us`` (int64 [N]), ``events_p`` (uint8 [N]),
    ``window_end_ts_us`` (int64 [T]), ``hist_uint8_unpadded`` (uint8 [T, 20, 240, 304]).
    """
    path = MINI_PATH if request.param == "mini" else RVT_T_PATH
    if not path.is_file():
        pytest.skip(f"reference fixture {path.name} not found at {path} (shared/ folder beside the repo root)")
    return _load_inputs(path)
