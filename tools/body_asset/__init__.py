"""Helpers of ``tools/export_body_asset.py`` (run by hand, not part of the installed package).

- :mod:`body_asset.blender`: MPFB2's walk cycle resolved from its Blender action (rotations, Bezier F-curves, bone
  bases, two-bone IK) into plain per-bone local rotations; numpy only, no anny and no Blender.
- :mod:`body_asset.settle`: the walk settled on the ground with davis_rig's own body model (``--settle-walk-only``).

The tool imports them as the package ``body_asset`` beside it (its own folder is first on ``sys.path`` when it runs).
"""
