"""Controls of the texture attack: measurements that say what an attack on a given detector can reach at all.

- :mod:`davis_rig.controls.planted` — a *selective* planted blind spot: the grids a trigger victim is fine-tuned on
  (the trigger's neighbourhood hidden, everything else detected) and the cell agreement that says whether an
  optimized texture found the trigger.
- :mod:`davis_rig.controls.feature_probe` — whether a detector's frozen backbone features tell the trigger's
  neighbourhood from random grids at all (a linear probe with whole clips held out; ``tools/trigger_feature_probe.py``).
- :mod:`davis_rig.controls.bounds` — the victim's baseline fingerprint (white / black / random / checker) and the
  free-appearance bound (per-pixel intensities, per-frame and static textures on the person, optimised freely per
  scene), and one texture shared by several scenes (grey or black/white).
- :mod:`davis_rig.controls.report` — a victim's controls as json + markdown (``tools/victim_controls.py``).
"""
