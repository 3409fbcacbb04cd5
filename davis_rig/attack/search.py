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
detector on the attack's EoT clips and writes a run folder like ``davis-attack optimize``'s.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

__all__ = ["SEARCH_SEED_OFFSET", "SearchSettings", "cem_update", "cross_entropy_search", "mean_entropy_bits",
           "mode_grid", "sample_grids", "search_texture"]

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


def cross_entropy_search(
    score: Callable[[np.ndarray, int], np.ndarray],
    probabilities: np.ndarray,
    cells: np.ndarray,
    settings: SearchSettings,
    rng: np.random.Generator,
    on_generation: Callable[[dict, np.ndarray], None] | None = None,
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

    Returns:
        float64 [n, n], the final probabilities.
    """
    p = np.asarray(probabilities, dtype=np.float64).copy()
    for generation in range(1, settings.generations + 1):
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


def search_texture(config, detector, out: str | Path, settings: SearchSettings, *, pool_clips: int = 32,
                   clips_per_grid: int = 8, validate_every: int = 5, motions: Sequence = (),
                   reference: np.ndarray | None = None, say: Callable[[str], None] = lambda message: None,
                   stop=None) -> dict:
    """The cross-entropy method against ``detector`` on the attack's EoT clips; writes a run folder.

    Each generation scores its grids on ``clips_per_grid`` clips drawn (the same for the whole generation) from a
    pool of ``pool_clips`` prepared clips of the attack's training distribution, by the mean top pedestrian score
    (highest ``obj * p_ped`` per window) with exact event counts from each clip's own sensor (what the refinement
    scores, :func:`davis_rig.attack.validation.validate`). Every ``validate_every`` generations, and after the
    last, the mode grid is validated on ``config.num_validation_clips`` clips — the same clips as
    ``davis-attack optimize`` with this seed validates on — and the best (``config.select_by``) is kept.

    Args:
        config: :class:`~davis_rig.attack.config.AttackConfig` (grid size, parts, EoT, seed, validation).
        detector: the frozen RVT detector.
        out: the run folder (created).
        settings: :class:`SearchSettings`.
        pool_clips: clips prepared for the search.
        clips_per_grid: clips each generation's grids are scored on (<= ``pool_clips``).
        validate_every: generations between validations.
        motions: training motions of the clips (default: the shapes' walk cycles).
        reference: float [n, n], a known grid (a planted trigger) each generation's mode is compared with
            (``agreement``: the share of searched cells where they agree); never shown to the search.
        say: progress messages.
        stop: a :class:`~davis_rig.stop.StopOnSignal`: a requested stop abandons the generation under way and
            writes the textures of the finished ones.

    Returns:
        ``{"best": validation record of the kept grid (None before the first validation), "generations": done,
        "seconds", "cells": searched, "stopped": whether a stop request ended it}``;
        the folder holds ``log.jsonl`` (a record per generation, validations included), ``probabilities.npy``,
        ``texture.npy/png`` (the final mode; none when stopped before the first generation ended),
        ``best_texture.npy/png`` + ``best.json`` (the kept one) and ``search.json`` (settings and summary).
    """
    from davis_rig.attack.checkpoint import write_texture_png
    from davis_rig.attack.refine import visible_cells
    from davis_rig.attack.validation import better, validate, validation_clips
    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.masks import part_mask
    from davis_rig.stop import StopRequested

    if not 1 <= clips_per_grid <= pool_clips:
        raise ValueError(f"clips_per_grid must be in [1, pool_clips={pool_clips}], got {clips_per_grid}")
    if reference is not None and np.shape(reference) != (config.grid_n, config.grid_n):
        raise ValueError(f"reference must be [{config.grid_n}, {config.grid_n}], got {list(np.shape(reference))}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    n = config.grid_n
    body = BodyModel()
    mask = part_mask(config.parts) if config.parts is not None else None
    say(f"preparing {pool_clips} search clips and {config.num_validation_clips} validation clips ({n}x{n})")
    pool = validation_clips(config, body, mask, pool_clips, SEARCH_SEED_OFFSET, motions)
    val = validation_clips(config, body, mask, config.num_validation_clips, motions=motions)
    cells = visible_cells(pool, n)
    train_path = (config.v2e_mode, config.v2e_binning)
    clip_rng = np.random.default_rng([config.seed, 1])

    def score(grids: np.ndarray, generation: int) -> np.ndarray:
        chosen = [pool[i] for i in clip_rng.choice(len(pool), clips_per_grid, replace=False)]
        return np.array([validate(grid, chosen, detector, config.validation_threshold, config.events,
                                  test_path=False, train_path=train_path, stop=stop)["train_top_score"]
                         for grid in grids])

    start = np.full((n, n), 0.5)
    state = {"best": None, "generations": 0, "probabilities": start}
    t0 = time.perf_counter()
    log = open(out / "log.jsonl", "w")

    def on_generation(record: dict, probabilities: np.ndarray) -> None:
        generation = record["generation"]
        if reference is not None:
            same = (np.asarray(record["mode"]) > 0.5) == (np.asarray(reference) > 0.5)
            record["agreement"] = float(same[cells].mean())
        if generation % validate_every == 0 or generation == settings.generations:
            grid = np.asarray(record["mode"], dtype=np.float32)
            res = validate(grid, val, detector, config.validation_threshold, config.events, train_path=train_path,
                           stop=stop)
            record["validation"] = res
            if better(res, state["best"], config.select_by):
                state["best"] = {**res, "generation": generation}
                np.save(out / "best_texture.npy", grid)
                write_texture_png(out / "best_texture.png", grid)
                (out / "best.json").write_text(json.dumps(state["best"], indent=1))
        log.write(json.dumps({**record, "seconds": time.perf_counter() - t0}) + "\n")
        log.flush()
        # the generation counts once logged: a stop during its validation leaves the previous one in force
        state["generations"], state["probabilities"] = generation, probabilities
        np.save(out / "probabilities.npy", probabilities)
        say(f"generation {generation}/{settings.generations}: scores {record['score_mean']:.3f} mean, "
            f"{record['score_best']:.3f} best, entropy {record['entropy_bits']:.2f} bit"
            + (f", agreement {record['agreement']:.2f}" if "agreement" in record else "")
            + (f"; validation {record['validation']['mean_top_score']:.3f}, SeqASR "
               f"{record['validation']['SeqASR']:.1%}" if "validation" in record else ""))

    stopped = False
    try:
        cross_entropy_search(score, start, cells, settings, np.random.default_rng(config.seed), on_generation)
    except StopRequested:  # keep what the finished generations found
        stopped = True
    finally:
        log.close()
    if state["generations"]:  # a stop before the first generation leaves no texture to show for it
        texture = mode_grid(state["probabilities"], cells)
        np.save(out / "texture.npy", texture)
        write_texture_png(out / "texture.png", texture)
    summary = {"settings": asdict(settings), "pool_clips": pool_clips, "clips_per_grid": clips_per_grid,
               "validate_every": validate_every, "cells": int(cells.sum()), "generations": state["generations"],
               "seconds": time.perf_counter() - t0, "stopped": stopped, "best": state["best"]}
    (out / "search.json").write_text(json.dumps(summary, indent=1))
    return {"best": state["best"], "generations": state["generations"], "seconds": summary["seconds"],
            "cells": int(cells.sum()), "stopped": stopped}

