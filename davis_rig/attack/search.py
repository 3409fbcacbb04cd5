"""Gradient-free search over black/white grids: the cross-entropy method on one probability per cell.

Beyond the paper. The paper's recipe follows the gradient of the loss through binarization, the event counts'
surrogate and RVT; on the planted victims measured here that gradient aims at the blind spot on barely more than
half of the cells, however many EoT clips average it (``docs/attack_results.md``). The cross-entropy method (CEM,
Rubinstein 1999; with smoothing, Baluja's PBIL) needs no gradient: it keeps the probability that each cell is
white, samples a population of hard grids from it, scores every grid on the same EoT clips with exact event
counts, and moves each probability towards the share of white in the best-scoring grids (the elite). Its step
follows how a cell's colour shifts the score *averaged over the grids the distribution draws*, not the slope at
one grid, and it only ever scores printable black/white grids.

:func:`cross_entropy_search` is the pure loop over a ``score`` callable; :func:`search_texture` runs it against a
detector on the attack's EoT clips and writes a run folder like ``davis-attack optimize``'s (``davis-attack search``),
which a stopped run continues from exactly (``state.json``: the probabilities, both random states and the best so
far after every generation). :func:`start_probabilities` starts the search around a given grid (e.g. the gradient
recipe's texture) instead of from no prior.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

__all__ = ["SEARCH_SEED_OFFSET", "SearchSettings", "cem_update", "cross_entropy_search", "mean_entropy_bits",
           "mode_grid", "sample_grids", "search_texture", "start_probabilities"]

#: Offset added to the run's seed: the search pool's clip seeds (apart from validation's and refinement's).
SEARCH_SEED_OFFSET = 3_000_017


@dataclass(frozen=True)
class SearchSettings:
    """The cross-entropy method's settings.

    Attributes:
        generations: populations sampled and scored.
        population: grids per generation (all scored on the same clips).
        elite: the best-scoring grids the probabilities move towards (1 <= elite <= population).
        smoothing: the step of each probability towards the elite's share of white, in (0, 1].
        floor: probabilities are kept in [floor, 1 - floor], so that no cell stops being tried (0 <= floor < 0.5).
    """

    generations: int = 40
    population: int = 12
    elite: int = 3
    smoothing: float = 0.3
    floor: float = 0.02

    def __post_init__(self) -> None:
        if self.generations < 1 or self.population < 2:
            raise ValueError(f"need generations >= 1 and population >= 2, got {self.generations}, {self.population}")
        if not 1 <= self.elite <= self.population:
            raise ValueError(f"elite must be in [1, population={self.population}], got {self.elite}")
        if not 0 < self.smoothing <= 1:
            raise ValueError(f"smoothing must be in (0, 1], got {self.smoothing}")
        if not 0 <= self.floor < 0.5:
            raise ValueError(f"floor must be in [0, 0.5), got {self.floor}")


def sample_grids(probabilities: np.ndarray, cells: np.ndarray, population: int, rng: np.random.Generator,
                 fill: float = 0.0) -> np.ndarray:
    """Hard grids drawn cell by cell: white with the cell's probability on ``cells``, ``fill`` elsewhere.

    Args:
        probabilities: float [n, n], P(white) per cell.
        cells: bool [n, n], the searched cells.
        population: grids drawn.
        rng: source of the draws.
        fill: the value of cells outside ``cells`` (they are never seen, so any fixed value).

    Returns:
        float32 [population, n, n] of 0 / 1 (and ``fill``).
    """
    p = np.asarray(probabilities, dtype=np.float64)
    white = rng.random((int(population), *p.shape)) < p
    return np.where(np.asarray(cells, bool), white, fill).astype(np.float32)


def cem_update(probabilities: np.ndarray, elite_grids: np.ndarray, cells: np.ndarray, smoothing: float,
               floor: float = 0.0) -> np.ndarray:
    """One smoothed cross-entropy step: ``p <- (1 - smoothing) p + smoothing * mean(elite)`` on ``cells``.

    Args:
        probabilities: float [n, n], P(white) per cell.
        elite_grids: float [k, n, n] of 0 / 1, the best-scoring grids.
        cells: bool [n, n], the searched cells (the others keep their probability).
        smoothing: step in (0, 1].
        floor: the result is clipped to [floor, 1 - floor] on ``cells``.

    Returns:
        float64 [n, n], the new probabilities.
    """
    p = np.asarray(probabilities, dtype=np.float64)
    target = np.asarray(elite_grids, dtype=np.float64).mean(axis=0)
    moved = np.clip((1.0 - smoothing) * p + smoothing * target, floor, 1.0 - floor)
    return np.where(np.asarray(cells, bool), moved, p)


def mode_grid(probabilities: np.ndarray, cells: np.ndarray, fill: float = 0.0) -> np.ndarray:
    """The distribution's most likely grid: white where P(white) > 0.5 on ``cells``, ``fill`` elsewhere.

    Returns:
        float32 [n, n].
    """
    white = np.asarray(probabilities) > 0.5
    return np.where(np.asarray(cells, bool), white, fill).astype(np.float32)


def mean_entropy_bits(probabilities: np.ndarray, cells: np.ndarray) -> float:
    """Mean binary entropy of the searched cells' probabilities, in bits (1: undecided, 0: settled)."""
    p = np.clip(np.asarray(probabilities, dtype=np.float64)[np.asarray(cells, bool)], 1e-12, 1 - 1e-12)
    return float(np.mean(-(p * np.log2(p) + (1 - p) * np.log2(1 - p))))


def start_probabilities(grid: np.ndarray, confidence: float, cells: np.ndarray) -> np.ndarray:
    """P(white) that starts the search around ``grid``: ``confidence`` on its white searched cells,
    ``1 - confidence`` on its black ones, 0.5 elsewhere (never drawn).

    Args:
        grid: float [n, n] black/white grid (> 0.5: white).
        confidence: in [0.5, 1): the probability that a draw keeps a cell's colour (0.5: no prior).
        cells: bool [n, n], the searched cells.

    Returns:
        float64 [n, n].

    Raises:
        ValueError: ``confidence`` outside [0.5, 1) or shapes that differ.
    """
    if not 0.5 <= confidence < 1.0:
        raise ValueError(f"confidence must be in [0.5, 1), got {confidence}")
    if np.shape(grid) != np.shape(cells):
        raise ValueError(f"the start grid is {list(np.shape(grid))}, the cells {list(np.shape(cells))}")
    white = np.asarray(grid) > 0.5
    return np.where(np.asarray(cells, bool), np.where(white, confidence, 1.0 - confidence), 0.5)


def cross_entropy_search(
    score: Callable[[np.ndarray, int], np.ndarray],
    probabilities: np.ndarray,
    cells: np.ndarray,
    settings: SearchSettings,
    rng: np.random.Generator,
    on_generation: Callable[[dict, np.ndarray], None] | None = None,
    first_generation: int = 1,
) -> np.ndarray:
    """The cross-entropy method over black/white grids, minimising ``score``.

    Args:
        score: ``score(grids [P, n, n], generation) -> float [P]``, lower is better; a generation's grids should be
            scored alike (the same clips), so that their ranking is paired.
        probabilities: float [n, n], the starting P(white) per cell (0.5: no prior).
        cells: bool [n, n], the searched cells.
        settings: :class:`SearchSettings`.
        rng: source of the grids.
        on_generation: called after each generation with its record (``generation`` from 1, ``score_mean``,
            ``score_best``, ``score_elite``, ``entropy_bits``, ``mode``: the mode grid after the update as a
            list of rows) and the updated probabilities.
        first_generation: the number of the first generation run (> 1: a run continued with the probabilities
            and ``rng`` state it had after generation ``first_generation - 1``).

    Returns:
        float64 [n, n], the final probabilities (the given ones when ``first_generation`` is past the last).
    """
    p = np.asarray(probabilities, dtype=np.float64).copy()
    for generation in range(int(first_generation), settings.generations + 1):
        grids = sample_grids(p, cells, settings.population, rng)
        values = np.asarray(score(grids, generation), dtype=np.float64)
        if values.shape != (settings.population,):
            raise ValueError(f"score returned shape {values.shape}, expected ({settings.population},)")
        order = np.argsort(values, kind="stable")
        p = cem_update(p, grids[order[: settings.elite]], cells, settings.smoothing, settings.floor)
        if on_generation is not None:
            record = {"generation": generation, "score_mean": float(values.mean()), "score_best": float(values.min()),
                      "score_elite": float(values[order[: settings.elite]].mean()),
                      "entropy_bits": mean_entropy_bits(p, cells),
                      "mode": mode_grid(p, cells).astype(int).tolist()}
            on_generation(record, p)
    return p


#: The run's state after its last finished generation, which ``resume=True`` continues from.
STATE_FILE = "state.json"
#: Outputs of a search run (besides :data:`STATE_FILE`): replaced when a new run starts in the folder.
SEARCH_OUTPUTS = ("log.jsonl", "probabilities.npy", "texture.npy", "texture.png", "best_texture.npy",
                  "best_texture.png", "best.json", "search.json")


def search_texture(config, detector, out: str | Path, settings: SearchSettings, *, pool_clips: int = 32,
                   clips_per_grid: int = 8, validate_every: int = 5, motions: Sequence = (),
                   reference: np.ndarray | None = None, start_grid: np.ndarray | None = None,
                   start_confidence: float = 0.9, resume: bool = False,
                   say: Callable[[str], None] = lambda message: None, stop=None) -> dict:
    """The cross-entropy method against ``detector`` on the attack's EoT clips; writes a run folder.

    Each generation scores its grids on ``clips_per_grid`` clips drawn (the same for the whole generation) from a
    pool of ``pool_clips`` prepared clips of the attack's training distribution, by the mean top pedestrian score
    (highest ``obj * p_ped`` per window) with exact event counts from each clip's own sensor (what the refinement
    scores, :func:`davis_rig.attack.validation.validate`). Every ``validate_every`` generations, and after the
    last, the mode grid is validated on ``config.num_validation_clips`` clips — the same clips as
    ``davis-attack optimize`` with this seed validates on — and the best (``config.select_by``) is kept; a
    ``start_grid`` is validated first (generation 0), so the run never returns worse than its start.

    After every generation ``state.json`` holds what the next one needs (the probabilities, the random states of
    the grids and the clip draws, the best so far, the settings): ``resume=True`` continues from it and scores the
    same grids on the same clips as a run that was never stopped. ``settings.generations`` and ``validate_every``
    may change on resume, nothing else; a resume that names no ``start_grid`` continues around the run's own (and
    with its ``start_confidence``).

    Args:
        config: :class:`~davis_rig.attack.config.AttackConfig` (grid size, parts, EoT, seed, validation).
        detector: the frozen RVT detector (the clips are prepared on its device).
        out: the run folder (created).
        settings: :class:`SearchSettings`.
        pool_clips: clips prepared for the search.
        clips_per_grid: clips each generation's grids are scored on (<= ``pool_clips``).
        validate_every: generations between validations.
        motions: training motions of the clips (default: the shapes' walk cycles).
        reference: float [n, n], a known grid (a planted trigger) each generation's mode is compared with
            (``agreement``: the share of searched cells where they agree); never shown to the search.
        start_grid: float [n, n] black/white grid the search starts around (:func:`start_probabilities`;
            ``None``: P(white) = 0.5 everywhere; on resume, ``None`` means the run's own start, as saved).
        start_confidence: P(a draw keeps the start grid's colour), in [0.5, 1).
        resume: continue the run in ``out`` (a new run when it holds none); ``False`` refuses a folder that holds
            one.
        say: progress messages.
        stop: a :class:`~davis_rig.stop.StopOnSignal`: a requested stop abandons the generation under way and
            writes the textures of the finished ones.

    Returns:
        ``{"best": validation record of the kept grid (None before the first validation), "generations": done,
        "seconds", "cells": searched, "stopped": whether a stop request ended it}``;
        the folder holds ``log.jsonl`` (a record per generation, validations included), ``probabilities.npy``,
        ``texture.npy/png`` (the final mode; none when stopped before the first generation ended),
        ``best_texture.npy/png`` + ``best.json`` (the kept one), ``search.json`` (settings and summary) and
        ``state.json``.

    Raises:
        ValueError: bad arguments (before any work).
        CheckpointError: ``out`` holds a run and ``resume`` is False; its ``state.json`` is unreadable or was
            written with other settings.
    """
    from davis_rig.attack.checkpoint import write_texture_png
    from davis_rig.attack.detector import detector_fingerprint
    from davis_rig.attack.refine import visible_cells
    from davis_rig.attack.validation import better, validate, validation_clips
    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.masks import part_mask
    from davis_rig.stop import StopRequested

    if not 1 <= clips_per_grid <= pool_clips:
        raise ValueError(f"clips_per_grid must be in [1, pool_clips={pool_clips}], got {clips_per_grid}")
    n = config.grid_n
    for name, grid in (("reference", reference), ("start_grid", start_grid)):
        if grid is not None and np.shape(grid) != (n, n):
            raise ValueError(f"{name} must be [{n}, {n}], got {list(np.shape(grid))}")
    if not 0.5 <= start_confidence < 1.0:
        raise ValueError(f"start_confidence must be in [0.5, 1), got {start_confidence}")
    out = Path(out)
    if resume and start_grid is None:
        start_grid, start_confidence = _saved_start(out, start_confidence)
    run_key = {"config": config.to_dict(), "pool_clips": pool_clips, "clips_per_grid": clips_per_grid,
               "motions": len(motions), "start_confidence": start_confidence if start_grid is not None else None,
               "start_grid": None if start_grid is None else (np.asarray(start_grid) > 0.5).astype(int).tolist(),
               "settings": {k: v for k, v in asdict(settings).items() if k != "generations"},
               "detector": detector_fingerprint(detector)}
    resumed = _resumed_state(out, resume, run_key)
    out.mkdir(parents=True, exist_ok=True)
    body = BodyModel(device=next(detector.parameters()).device)
    mask = part_mask(config.parts) if config.parts is not None else None
    say(f"preparing {pool_clips} search clips and {config.num_validation_clips} validation clips ({n}x{n})")
    pool = validation_clips(config, body, mask, pool_clips, SEARCH_SEED_OFFSET, motions)
    val = validation_clips(config, body, mask, config.num_validation_clips, motions=motions)
    cells = visible_cells(pool, n)
    train_path = (config.v2e_mode, config.v2e_binning)
    grid_rng, clip_rng = np.random.default_rng(config.seed), np.random.default_rng([config.seed, 1])

    def score(grids: np.ndarray, generation: int) -> np.ndarray:
        chosen = [pool[i] for i in clip_rng.choice(len(pool), clips_per_grid, replace=False)]
        return np.array([validate(grid, chosen, detector, config.validation_threshold, config.events,
                                  test_path=False, train_path=train_path, stop=stop)["train_top_score"]
                         for grid in grids])

    if resumed is not None:
        state = {"best": resumed["best"], "generations": resumed["generation"],
                 "probabilities": np.asarray(resumed["probabilities"], dtype=np.float64)}
        grid_rng.bit_generator.state, clip_rng.bit_generator.state = resumed["grid_rng"], resumed["clip_rng"]
        _truncate_search_log(out / "log.jsonl", state["generations"])
        say(f"resuming after generation {state['generations']}")
    else:
        for name in SEARCH_OUTPUTS:
            (out / name).unlink(missing_ok=True)
        start = (np.full((n, n), 0.5) if start_grid is None
                 else start_probabilities(start_grid, start_confidence, cells))
        state = {"best": None, "generations": 0, "probabilities": start}
    seconds_before = resumed["seconds"] if resumed is not None else 0.0
    t0 = time.perf_counter()
    log = open(out / "log.jsonl", "a")

    def keep_if_better(res: dict, grid: np.ndarray, generation: int) -> None:
        if better(res, state["best"], config.select_by):
            state["best"] = {**res, "generation": generation}
            np.save(out / "best_texture.npy", grid)
            write_texture_png(out / "best_texture.png", grid)
            (out / "best.json").write_text(json.dumps(state["best"], indent=1))

    def finish(record: dict, generation: int, probabilities: np.ndarray) -> None:
        """Log the generation, then make it the state a resume starts from."""
        seconds = seconds_before + time.perf_counter() - t0
        log.write(json.dumps({**record, "seconds": seconds}) + "\n")
        log.flush()
        state["generations"], state["probabilities"] = generation, probabilities
        np.save(out / "probabilities.npy", probabilities)
        _write_json_atomic(out / STATE_FILE, {
            **run_key, "generation": generation, "probabilities": probabilities.tolist(), "best": state["best"],
            "grid_rng": grid_rng.bit_generator.state, "clip_rng": clip_rng.bit_generator.state, "seconds": seconds})

    def on_generation(record: dict, probabilities: np.ndarray) -> None:
        generation = record["generation"]
        if reference is not None:
            same = (np.asarray(record["mode"]) > 0.5) == (np.asarray(reference) > 0.5)
            record["agreement"] = float(same[cells].mean())
        if generation % validate_every == 0 or generation == settings.generations:
            grid = np.asarray(record["mode"], dtype=np.float32)
            record["validation"] = validate(grid, val, detector, config.validation_threshold, config.events,
                                            train_path=train_path, stop=stop)
            keep_if_better(record["validation"], grid, generation)
        # the generation counts once logged: a stop during its validation leaves the previous one in force
        finish(record, generation, probabilities)
        say(f"generation {generation}/{settings.generations}: scores {record['score_mean']:.3f} mean, "
            f"{record['score_best']:.3f} best, entropy {record['entropy_bits']:.2f} bit"
            + (f", agreement {record['agreement']:.2f}" if "agreement" in record else "")
            + (f"; validation {record['validation']['mean_top_score']:.3f}, SeqASR "
               f"{record['validation']['SeqASR']:.1%}" if "validation" in record else ""))

    stopped = False
    try:
        if resumed is None and start_grid is not None:  # generation 0: the start itself, so no run returns worse
            grid = mode_grid(state["probabilities"], cells)
            res = validate(grid, val, detector, config.validation_threshold, config.events, train_path=train_path,
                           stop=stop)
            keep_if_better(res, grid, 0)
            finish({"generation": 0, "start": True, "mode": grid.astype(int).tolist(), "validation": res}, 0,
                   state["probabilities"])
            say(f"start: validation {res['mean_top_score']:.3f}, SeqASR {res['SeqASR']:.1%}")
        cross_entropy_search(score, state["probabilities"], cells, settings, grid_rng, on_generation,
                             first_generation=state["generations"] + 1)
    except StopRequested:  # keep what the finished generations found
        stopped = True
    finally:
        log.close()
    if state["generations"]:  # a stop before the first generation leaves no texture to show for it
        texture = mode_grid(state["probabilities"], cells)
        np.save(out / "texture.npy", texture)
        write_texture_png(out / "texture.png", texture)
    seconds = seconds_before + time.perf_counter() - t0
    summary = {"settings": asdict(settings), "pool_clips": pool_clips, "clips_per_grid": clips_per_grid,
               "validate_every": validate_every, "start_confidence": run_key["start_confidence"],
               "cells": int(cells.sum()), "generations": state["generations"], "seconds": seconds,
               "stopped": stopped, "best": state["best"]}
    (out / "search.json").write_text(json.dumps(summary, indent=1))
    return {"best": state["best"], "generations": state["generations"], "seconds": seconds,
            "cells": int(cells.sum()), "stopped": stopped}


def _write_json_atomic(path: Path, obj) -> None:
    """Write ``obj`` as JSON to a temporary file beside ``path``, then rename it over ``path``."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj))
    os.replace(tmp, path)


def _saved_start(out: Path, start_confidence: float) -> tuple[np.ndarray | None, float]:
    """The start grid and confidence saved in ``out``'s state (``(None, start_confidence)``: a run without a start,
    or no readable state, which :func:`_resumed_state` then judges)."""
    try:
        state = json.loads((out / STATE_FILE).read_text())
        grid, confidence = state["start_grid"], state["start_confidence"]
    except (OSError, ValueError, TypeError, KeyError):
        return None, start_confidence
    if grid is None or not isinstance(confidence, float):
        return None, start_confidence
    return np.asarray(grid, dtype=np.float32), confidence


def _resumed_state(out: Path, resume: bool, run_key: dict) -> dict | None:
    """The state a run in ``out`` continues from (``None``: a new run), after the checks of :func:`search_texture`.

    Raises:
        CheckpointError: ``out`` holds a run and ``resume`` is False; ``state.json`` is unreadable, malformed or
            written with other settings; the log records generations that no state follows.
    """
    from davis_rig.errors import CheckpointError

    path, log = out / STATE_FILE, out / "log.jsonl"
    logged = log.is_file() and log.stat().st_size > 0
    if not resume:
        if path.is_file() or logged:
            raise CheckpointError(f"{out} already holds a search ({path if path.is_file() else log}); continue it "
                                  f"with --resume (resume=True) or write the new run to another --out folder")
        return None
    if not path.is_file():
        if logged:
            raise CheckpointError(f"{log} records generations but there is no {path} to continue from; remove {out} "
                                  f"or start again in another --out folder")
        return None
    try:
        state = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise CheckpointError(f"{path}: unreadable search state ({type(exc).__name__}: {exc})") from exc
    # "detector": a state written before the fingerprint was kept has none to check
    keys = ("generation", "probabilities", "best", "grid_rng", "clip_rng", "seconds",
            *(k for k in run_key if k != "detector"))
    if not isinstance(state, dict) or any(k not in state for k in keys):
        raise CheckpointError(f"{path}: not a search state (missing: "
                              f"{[k for k in keys if not isinstance(state, dict) or k not in state]})")
    if state.get("detector", run_key["detector"]) != run_key["detector"]:
        raise CheckpointError(f"{path} was written against another detector (weights {state['detector']}, the "
                              f"given one {run_key['detector']}): resume with the run's --detector, or start the new "
                              "one in another --out folder")
    differ = sorted(k for k in run_key if k in state and state[k] != run_key[k])
    if differ:
        raise CheckpointError(f"{path} was written with other settings ({', '.join(differ)}); only --generations "
                              f"and --validate-every may change on resume")
    n = run_key["config"]["grid_n"]
    if np.shape(state["probabilities"]) != (n, n) or not isinstance(state["generation"], int):
        raise CheckpointError(f"{path}: malformed probabilities or generation")
    return state


def _truncate_search_log(path: Path, last_generation: int) -> None:
    """Drop log records after ``last_generation`` (a generation logged but never made the state is redone)."""
    if path.is_file():
        kept = [line for line in path.read_text().splitlines() if json.loads(line)["generation"] <= last_generation]
        path.write_text("".join(line + "\n" for line in kept))
