"""Controls of the texture attack: measurements that say what an attack on a given detector can reach at all.

- :mod:`davis_rig.controls.planted` — a *selective* planted blind spot: the grids a trigger victim is fine-tuned on
  (the trigger's neighbourhood hidden, everything else detected) and the cell agreement that says whether an
  optimized texture found the trigger.
- :mod:`davis_rig.controls.bounds` — the victim's baseline fingerprint (white / black / random / checker) and the
  free-appearance bound (per-pixel intensities and per-frame textures on the person, optimised freely per clip).
"""
