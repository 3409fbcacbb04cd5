"""The digital optimizer: adversarial texture, loss and print export.

Modules:

- :mod:`~davis_rig.attack.texture` (torch): ``TextureGenerator`` (the paper's generation block),
  ``binarize_ste`` and alpha schedules, ``upsample_grid``, ``apply_part_mask``, baseline textures.
- :mod:`~davis_rig.attack.loss` (torch): ``adversarial_loss`` on the detector's decoded output.
- :mod:`~davis_rig.attack.export` (numpy + reportlab): print-ready vector PDF pattern pieces, PNG textures,
  preview render.

Importing this package imports neither torch nor reportlab; the names below are loaded on first access.
"""

from __future__ import annotations

from davis_rig._lazy import lazy_exports

_LAZY = {
    "davis_rig.attack.texture": (
        "TextureGenerator", "binarize_ste", "alpha_at", "upsample_grid", "apply_part_mask", "white_texture",
        "black_texture", "random_texture",
    ),
    "davis_rig.attack.loss": ("adversarial_loss", "AdversarialLoss"),
    "davis_rig.attack.export": ("export_texture", "load_texture_grid", "pattern_pieces", "write_pattern_pdf"),
}  # fmt: skip

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

__all__ = sorted(name for names in _LAZY.values() for name in names)
