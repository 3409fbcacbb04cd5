"""An attack run's folder: the checkpoint ``checkpoints/last.pt``, the log ``log.jsonl`` and the texture outputs.

- :func:`read_attack_checkpoint` / :func:`atomic_save`: the checkpoint (generator, optimizer, completed steps, pool
  generations, best so far, config), written atomically;
- :func:`check_resume_config`: a resume only continues a run written with the same settings
  (:data:`FREE_ON_RESUME` may change; fields added later count as their default or legacy value);
- :func:`check_new_run`, :func:`truncate_log`, :func:`clear_outputs`, :func:`remove_unfinished`: the folder at the
  start of a call (a new run neither appends to an old log nor finds its textures) and after a new run that failed
  before its first checkpoint (nothing left behind);
- :func:`final_validation`, :func:`write_texture_png`: the run's records and texture images.
"""

from __future__ import annotations

import json
import os
from dataclasses import MISSING, asdict, fields
from pathlib import Path

import numpy as np

from davis_rig._lazy import optional_dependency
from davis_rig.attack.config import AttackConfig
from davis_rig.attack.eot import EoTConfig
from davis_rig.errors import CheckpointError

with optional_dependency("the attack"):
    import torch

__all__ = [
    "FREE_ON_RESUME",
    "RUN_OUTPUTS",
    "atomic_save",
    "check_new_run",
    "check_resume_config",
    "clear_outputs",
    "final_validation",
    "logged_steps",
    "read_attack_checkpoint",
    "remove_unfinished",
    "truncate_log",
    "write_texture_png",
]


def atomic_save(obj, path: Path) -> None:
    """``torch.save`` to a temporary file beside ``path``, then rename it over ``path`` (a reader never sees half a
    file; the parent folder is created)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


#: Keys of ``checkpoints/last.pt`` and their types (``pending_validation``, added later, is optional).
_CHECKPOINT_KEYS = {"generator": dict, "optimizer": dict, "step": int, "pool": dict, "best": str, "config": dict}


def read_attack_checkpoint(path: str | Path, map_location=None) -> dict:
    """Read an attack run's ``checkpoints/last.pt`` and check its layout.

    Args:
        path: the checkpoint.
        map_location: torch ``map_location`` of its tensors.

    Returns:
        The state dict: ``generator``, ``optimizer`` (state dicts), ``step`` (completed steps), ``pool``
        (``{"base_seed", "size", "generations"}``), ``best`` (JSON of the best validation record or ``""``),
        ``config`` (:meth:`AttackConfig.to_dict`), ``pending_validation`` (bool: the validation of ``step`` was
        interrupted and runs first on resume).

    Raises:
        CheckpointError: unreadable (truncated, corrupt) or not an attack checkpoint; the message names ``path``.
    """
    path = Path(path)
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # torch raises UnpicklingError, RuntimeError, EOFError, ... depending on the damage
        first = (str(exc).strip().splitlines() or [""])[0]  # torch's messages run over several lines
        raise CheckpointError(f"{path}: unreadable attack checkpoint ({type(exc).__name__}: {first})") from exc
    if not isinstance(state, dict):
        raise CheckpointError(f"{path}: not an attack checkpoint (a {type(state).__name__}, not a dict)")
    wrong = sorted(k for k, kind in _CHECKPOINT_KEYS.items() if not isinstance(state.get(k), kind))
    if wrong:
        raise CheckpointError(f"{path}: not an attack checkpoint (missing or malformed: {', '.join(wrong)})")
    pool = state["pool"]
    if not isinstance(pool.get("generations"), list) or not isinstance(state["config"].get("eot"), dict):
        raise CheckpointError(f"{path}: not an attack checkpoint (malformed pool or config)")
    if state["step"] < 0:
        raise CheckpointError(f"{path}: negative step {state['step']}")
    try:
        json.loads(state["best"]) if state["best"] else None
    except ValueError as exc:
        raise CheckpointError(f"{path}: malformed best record ({exc})") from exc
    state.setdefault("pending_validation", False)
    return state


#: Settings that may change when a run is resumed (the others must match the checkpoint's).
FREE_ON_RESUME = ("iterations", "refine_passes", "refine_clips", "checkpoint_every", "checkpoint_interval_s",
                  "detector_step")


#: Fields whose default changed after runs were written without them: the value such a run used. A checkpoint
#: that lacks another field counts it as its (unchanged) default.
_LEGACY_VALUES = {"lr_schedule": "constant"}


#: The same for the fields of ``eot``.
_LEGACY_EOT_VALUES = {"test_sensor_probability": 0.0, "walk": "bundled"}


def check_resume_config(state: dict, config: AttackConfig, path: Path) -> None:
    """Refuse a checkpoint written with other settings (naming the fields that differ).

    A field added after the checkpoint was written (top level or in ``eot``) counts as its default value, or as
    the value runs used before it existed (:data:`_LEGACY_VALUES`).
    """
    current = config.to_dict()
    defaults = json.loads(json.dumps({f.name: f.default for f in fields(AttackConfig) if f.default is not MISSING},
                                     default=str))
    saved = {**defaults, **_LEGACY_VALUES, **dict(state["config"])}
    saved["eot"] = {**json.loads(json.dumps(asdict(EoTConfig()), default=str)), **_LEGACY_EOT_VALUES,
                    **dict(saved["eot"])}
    for name in FREE_ON_RESUME:
        saved.pop(name, None)
        current.pop(name, None)
    if saved != current:
        diff = sorted(k for k in current if saved.get(k) != current.get(k))
        raise CheckpointError(f"{path} was written with a different configuration (fields {diff})")


def logged_steps(path: Path) -> int:
    """The last step recorded in a run's ``log.jsonl`` (0 when there is none)."""
    last = 0
    if path.is_file():
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except ValueError:
                continue
            if isinstance(rec, dict) and isinstance(rec.get("step"), int):
                last = max(last, rec["step"])
    return last


def truncate_log(path: Path, last_step: int) -> None:
    """Drop log records after ``last_step`` (written after the checkpoint a resume starts from)."""
    if not path.is_file():
        return
    kept = []
    for line in path.read_text().splitlines():
        rec = json.loads(line)
        if int(rec.get("validation", rec).get("step", 0)) <= last_step:
            kept.append(line)
    path.write_text("".join(k + "\n" for k in kept))


#: Outputs of a run (besides ``checkpoints/``): removed when a run starts from step 0 (:func:`clear_outputs`).
RUN_OUTPUTS = ("log.jsonl", "best_texture.npy", "best_texture.png", "best.json", "best_generator.pt", "refine.json",
               "refined_texture.npy", "refined_texture.png", "texture.npy", "texture.png")


def check_new_run(out: Path, resume: bool) -> None:
    """Refuse a new run (``resume=False``) in a folder that holds one (``checkpoints/last.pt`` or ``log.jsonl``),
    a resume of a run that logged steps but left no checkpoint (it would silently restart at step 1), and any run
    without a checkpoint to continue from in a folder holding another run's outputs (a search's, which starting
    from step 0 would delete).

    Raises:
        CheckpointError: the message names the folder and what to do.
    """
    ckpt = out / "checkpoints" / "last.pt"
    held = [p for p in (ckpt, out / "log.jsonl") if p.is_file()]
    if held and not resume:
        raise CheckpointError(f"{out} already holds a run ({held[0]}); continue it with --resume (resume=True) or "
                              f"write the new run to another --out folder")
    logged = logged_steps(out / "log.jsonl")
    if resume and not ckpt.is_file() and logged:
        raise CheckpointError(f"{out}/log.jsonl records {logged} steps but there is no {ckpt} to continue from (the "
                              f"run ended before its first checkpoint); remove {out} or start again in another --out "
                              f"folder")
    if not ckpt.is_file():  # a run starting from step 0 clears RUN_OUTPUTS: never those of another run or tool
        foreign = [name for name in (*RUN_OUTPUTS, "state.json", "search.json") if (out / name).is_file()]
        if foreign:
            raise CheckpointError(f"{out} holds {', '.join(foreign)} of another run (a search, or a run with no "
                                  f"checkpoint) and no {ckpt} to continue from: write this run to another --out "
                                  "folder")


def clear_outputs(out: Path) -> None:
    """Remove the outputs of an earlier run that left no checkpoint (:data:`RUN_OUTPUTS`, ``snapshots/step_*.png``),
    so a run starting from step 0 neither appends to its log nor finds its best, refined or final texture."""
    for name in RUN_OUTPUTS:
        (out / name).unlink(missing_ok=True)
    for snapshot in (out / "snapshots").glob("step_*.png"):
        snapshot.unlink()


def remove_unfinished(out: Path, created: bool) -> None:
    """Undo a new run that failed before its first checkpoint: its outputs, and the folders it created."""
    clear_outputs(out)
    for folder in (out / "snapshots", out / "checkpoints"):
        if folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
    if created and out.is_dir() and not any(out.iterdir()):
        out.rmdir()


def final_validation(log_path: Path, iterations: int) -> dict | None:
    """The last gradient-phase validation record of step ``iterations`` in a run's log (``None`` if none)."""
    found = None
    if log_path.is_file():
        for line in log_path.read_text().splitlines():
            rec = json.loads(line).get("validation")
            if rec is not None and rec.get("step") == iterations and not rec.get("refined"):
                found = rec
    return found


def write_texture_png(path: Path, grid: np.ndarray) -> None:
    """Write a texture grid as a black/white PNG, one pixel per cell (values > 0.5 white); creates the folder."""
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), (np.asarray(grid) > 0.5).astype(np.uint8) * 255)
