"""Fixtures of the viewer tests (the helper module is tests.helpers.viewer_data)."""

from pathlib import Path

import pytest

from tests.helpers.viewer_data import CHROMIUM_INSTALL, Chromium, chromium_binary, write_scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """A labelled scene session (one per test module; treat as read-only)."""
    return write_scene(tmp_path_factory.mktemp("scene") / "scene.h5")


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    """A headless chromium (skips with the install line when chromium is not installed)."""
    if chromium_binary() is None:
        pytest.skip(f"chromium is not installed ({CHROMIUM_INSTALL}); the browser tests need it")
    with Chromium(tmp_path_factory.mktemp("chromium-profile")) as chromium:
        yield chromium
