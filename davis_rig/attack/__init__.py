"""The digital optimizer: adversarial texture, loss and print export (issue 8).

Modules:

- :mod:`~davis_rig.attack.texture` (torch): ``TextureGenerator`` (the paper's generation block),
  ``binarize_ste`` and alpha schedules, ``upsample_grid``, ``apply_part_mask``, baseline textures.
- :mod:`~davis_rig.attack.loss` (torch): ``adversarial_loss`` on the detector's decoded output.
- :mod:`~davis_rig.attack.export` (numpy + reportlab): print-ready vector PDF pattern pieces, PNG textures,
  preview render.

Importing this package imports neither torch nor reportlab; the names below are loaded on first access.
"""

from __future__ import annotations

import importlib

_LAZY = {
    "TextureGenerator": "davis_rig.attack.texture",
    "binarize_ste": "davis_rig.attack.texture",
    "alpha_at": "davis_rig.attack.texture",
    "upsample_grid": "davis_rig.attack.texture",
    "apply_part_mask": "davis_rig.attack.texture",
    "white_texture": "davis_rig.attack.texture",
    "black_texture": "davis_rig.attack.texture",
    "random_texture": "davis_rig.attack.texture",
    "adversarial_loss": "davis_rig.attack.loss",
    "AdversarialLoss": "davis_rig.attack.loss",
    "export_texture": "davis_rig.attack.export",
    "load_texture_grid": "davis_rig.attack.export",
    "pattern_pieces": "davis_rig.attack.export",
    "write_pattern_pdf": "davis_rig.attack.export",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
