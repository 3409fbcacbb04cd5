"""davis_rig.events exports its modules' public API; importing it does not import torch."""

from __future__ import annotations

import importlib

import pytest

import davis_rig.events as events

MODULES = ("crop", "histogram", "histogram_torch", "intensity", "simulator", "v2e_torch")


def test_all_is_the_union_of_the_modules_public_names():
    expected = {name for m in MODULES for name in importlib.import_module(f"davis_rig.events.{m}").__all__}
    assert sorted(events.__all__) == sorted(expected) and len(events.__all__) == len(expected)


@pytest.mark.parametrize("module", MODULES)
def test_every_name_is_the_modules_object(module):
    mod = importlib.import_module(f"davis_rig.events.{module}")
    for name in mod.__all__:
        assert getattr(events, name) is getattr(mod, name), name
    assert set(mod.__all__) <= set(dir(events))


def test_unknown_name_raises_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'not_a_kernel'"):
        events.not_a_kernel  # noqa: B018


def test_import_does_not_import_torch_and_works_with_torch_blocked(fresh_python):
    code = (
        "import sys\n"
        "import davis_rig.events as e\n"
        "assert 'torch' not in sys.modules, 'import davis_rig.events imported torch'\n"
        "e.stacked_histograms\n"
        "assert 'torch' not in sys.modules, 'a numpy kernel imported torch'\n"
        "sys.modules['torch'] = None  # any 'import torch' now raises ImportError\n"
        "from davis_rig.events import simulate_events, v2e_histograms\n"
        "print('ok')\n"
    )
    assert fresh_python(code) == "ok"
