"""Shared fixtures for the RVT tests: the reference tensors produced by the official uzh-rpg/RVT code.

``mini_fixture``: ``tests/fixtures/rvt_mini_fixture.safetensors`` (in the repo, a reduced RVT config).
``rvt_t_fixture`` / ``rvt_t_grad_fixture``: the RVT-T fixture files in the ``shared/rvt/`` folder beside the
repository root; the tests that use them are skipped (with the reason) when that folder is absent.
``mini_onnx``: the mini fixture's model exported as an RVT step graph (``export_step_onnx``), once per run.

Each fixture is a :class:`RVTFixture`: ``fx[key]`` gives a numpy array (no torch needed), ``fx.tensor(key)`` a
torch tensor, ``fx.state_dict()`` the model weights with the Lightning ``mdl.`` prefix removed, ``fx.metadata``
the safetensors metadata (str → str) and ``fx.config`` the parsed ``metadata["config"]`` JSON (or ``None``).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[3]
FIXTURES_DIR = REPO_ROOT / "tests" / "fixtures"
SHARED_RVT_DIR = (REPO_ROOT / ".." / "shared" / "rvt").resolve()

MINI_FIXTURE_PATH = FIXTURES_DIR / "rvt_mini_fixture.safetensors"
RVT_T_FIXTURE_PATH = SHARED_RVT_DIR / "rvt_t_fixture.safetensors"
RVT_T_GRAD_FIXTURE_PATH = SHARED_RVT_DIR / "rvt_t_fixture_grad.safetensors"

STATE_DICT_PREFIX = "state_dict.mdl."


class RVTFixture:
    """Read-only view of one reference safetensors file (arrays are loaded once, on creation).

    Attributes:
        path: the file.
        metadata: safetensors metadata, str → str.
        config: ``json.loads(metadata["config"])`` when present, else ``None``.
    """

    def __init__(self, path: Path):
        from safetensors import safe_open

        self.path = path
        with safe_open(str(path), framework="np") as handle:
            self.metadata: dict[str, str] = dict(handle.metadata() or {})
            self._arrays = {key: handle.get_tensor(key) for key in handle.keys()}
        raw_config = self.metadata.get("config")
        self.config = json.loads(raw_config) if raw_config else None

    def keys(self) -> list[str]:
        """All tensor names in the file, sorted."""
        return sorted(self._arrays)

    def __contains__(self, key: str) -> bool:
        return key in self._arrays

    def __getitem__(self, key: str):
        """The stored array ``key`` as a numpy array (a read-only view; copy before modifying)."""
        array = self._arrays[key]
        array.flags.writeable = False
        return array

    def tensor(self, key: str):
        """The stored array ``key`` as a new torch tensor (a copy)."""
        import torch

        return torch.from_numpy(self._arrays[key].copy())

    def state_dict(self) -> dict:
        """The stored model weights (``state_dict.mdl.*``) as torch tensors, keys without ``state_dict.mdl.``."""
        return {
            key[len(STATE_DICT_PREFIX) :]: self.tensor(key)
            for key in self.keys()
            if key.startswith(STATE_DICT_PREFIX)
        }

    @property
    def num_steps(self) -> int:
        """Number of recorded recurrent steps (``step{t}.*`` groups)."""
        return len({key.split(".", 1)[0] for key in self._arrays if key.startswith("step")})


def _load_or_skip(path: Path) -> RVTFixture:
    if not path.is_file():
        pytest.skip(
            f"reference fixture {path.name} not found at {path} "
            "(it lives in the shared/ folder beside the repository root; CI has it there)"
        )
    return RVTFixture(path)


@pytest.fixture(scope="session")
def mini_fixture() -> RVTFixture:
    """The in-repo mini RVT fixture (reduced config, official code paths, 3 steps)."""
    return RVTFixture(MINI_FIXTURE_PATH)


@pytest.fixture(scope="session")
def rvt_t_fixture() -> RVTFixture:
    """The RVT-T gen1 fixture from ``shared/rvt/`` (skips when absent)."""
    return _load_or_skip(RVT_T_FIXTURE_PATH)


@pytest.fixture(scope="session")
def rvt_t_grad_fixture() -> RVTFixture:
    """The RVT-T input-gradient fixture from ``shared/rvt/`` (skips when absent)."""
    return _load_or_skip(RVT_T_GRAD_FIXTURE_PATH)


@pytest.fixture(scope="session")
def mini_onnx(tmp_path_factory) -> Path:
    """The mini fixture's detector as an RVT step ONNX file (needs torch and onnx; read it, do not modify it)."""
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from davis_rig.models.rvt.checkpoint import load_detector
    from davis_rig.models.rvt.onnx_export import export_step_onnx

    path = tmp_path_factory.mktemp("mini_onnx") / "rvt_mini_step.onnx"
    return export_step_onnx(load_detector(MINI_FIXTURE_PATH), path)
