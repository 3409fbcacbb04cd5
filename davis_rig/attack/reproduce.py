"""Reproduce the paper's Tables 1 and 2 in one call: optimize every texture a table needs, then evaluate it.

The budget is explicit: the :class:`~davis_rig.attack.optimize.AttackConfig` template carries the iterations,
learning rate, pool and validation settings, and the :class:`~davis_rig.attack.evaluate.EvalConfig` the test
scenes. A CPU run with a few hundred iterations and a GPU run with the paper's 11,500 use the same code.

Layout of ``out_dir``::

    runs/<n>x<n>_<parts>/   one optimize run per texture (davis_rig.attack.optimize layout); an existing run is
                            resumed, a finished one only re-read, so a second call continues where one stopped
                            and Table 2's full-body run is Table 1's 10 x 10 run
    table1.{md,json,png} or table2.{md,json,png}    (davis_rig.attack.report.table1 / table2)
    reproduce_table1.json or reproduce_table2.json  budget, detector, configs and per-run timing and validation

Table 1 (paper): white / black / random 60 x 60 baselines vs optimized full-body textures of grid 60, 50, 40, 30,
20 and 10 at thresholds 0.001 ... 0.25. Table 2: the 7 body-part combinations at 10 x 10, threshold 0.25.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import replace
from pathlib import Path
from typing import Sequence

import numpy as np

from davis_rig.attack.evaluate import EVENT_MODEL_NAMES, TABLE2_THRESHOLD, EvalConfig, config_dict
from davis_rig.attack.optimize import AttackConfig, optimize_texture
from davis_rig.attack.report import table1, table2
from davis_rig.scene.masks import PAINTABLE_COMBINATIONS, PAINTABLE_PARTS

__all__ = ["TABLE1_GRIDS", "TABLE2_GRID", "reproduce_table", "run_key", "table_runs"]

#: Grid sizes of the paper's Table 1 (cells per side).
TABLE1_GRIDS = (60, 50, 40, 30, 20, 10)
#: Grid size of Table 2.
TABLE2_GRID = 10


def run_key(grid_n: int, parts: Sequence[str]) -> str:
    """Folder name of the run of one texture, e.g. ``"10x10_torso+arms+legs"``."""
    return f"{int(grid_n)}x{int(grid_n)}_{'+'.join(parts)}"


def table_runs(table: int, *, grids: Sequence[int] | None = None,
               combinations: Sequence[Sequence[str]] | None = None) -> dict[str, tuple[int, tuple[str, ...]]]:
    """The optimize runs a table needs: run key -> ``(grid_n, parts)``.

    Args:
        table: 1 or 2.
        grids: Table 1 grid sizes (default :data:`TABLE1_GRIDS`, largest first).
        combinations: Table 2 part combinations (default all 7 of
            :data:`~davis_rig.scene.masks.PAINTABLE_COMBINATIONS`), each a subset of ``("torso", "arms", "legs")``.

    Returns:
        ordered dict of run keys (the table's row order).

    Raises:
        ValueError: table not 1 or 2, an empty selection, or an unknown part.
    """
    if table == 1:
        sizes = tuple(int(n) for n in (TABLE1_GRIDS if grids is None else grids))
        if not sizes:
            raise ValueError("grids must not be empty")
        return {run_key(n, PAINTABLE_PARTS): (n, PAINTABLE_PARTS) for n in sorted(set(sizes), reverse=True)}
    if table == 2:
        combos = PAINTABLE_COMBINATIONS if combinations is None else tuple(tuple(c) for c in combinations)
        if not combos:
            raise ValueError("combinations must not be empty")
        out = {}
        for combo in combos:
            unknown = sorted(set(combo) - set(PAINTABLE_PARTS))
            if unknown or not combo:
                raise ValueError(f"a combination is a non-empty subset of {PAINTABLE_PARTS}, got {combo}")
            parts = tuple(p for p in PAINTABLE_PARTS if p in combo)  # canonical order
            out[run_key(TABLE2_GRID, parts)] = (TABLE2_GRID, parts)
        return out
    raise ValueError(f"table must be 1 or 2, got {table!r}")


def reproduce_table(
    table: int,
    detector,
    out_dir: str | Path,
    *,
    attack: AttackConfig | None = None,
    eval_config: EvalConfig | None = None,
    grids: Sequence[int] | None = None,
    combinations: Sequence[Sequence[str]] | None = None,
    body_model=None,
    train_motions: Sequence = (),
    test_motions: Sequence = (),
    detector_name: str | None = None,
    command: str | None = None,
    progress: bool = False,
) -> dict:
    """Optimize every texture of Table 1 or 2 (resuming existing runs), then evaluate the table.

    Args:
        table: 1 or 2.
        detector: frozen RVT detector (:func:`~davis_rig.attack.optimize.load_attack_detector`).
        out_dir: output folder (module docstring).
        attack: the budget template (default :class:`AttackConfig`: the paper's 11,500 iterations); ``grid_n``
            and ``parts`` are set per run.
        eval_config: test scenes and thresholds (default: :class:`EvalConfig`; Table 2: threshold 0.25).
        grids, combinations: subsets of the table's rows (:func:`table_runs`).
        body_model: :class:`~davis_rig.scene.body.BodyModel` (default: bundled asset on the detector's device).
        train_motions, test_motions: EoT training motions and evaluation motions (default: walk cycles).
        detector_name: how the detector is named in the record (e.g. its path).
        command: the command line recorded in the markdown.
        progress: progress bars.

    Returns:
        ``{"markdown", "json", "plot", "rows"}`` of the table plus ``"record"`` (path of
        ``reproduce_table<k>.json``) and ``"runs"`` (run key -> per-run record).
    """
    from davis_rig.scene.body import BodyModel

    runs = table_runs(table, grids=grids, combinations=combinations)
    attack = attack or AttackConfig()
    if eval_config is None:
        eval_config = EvalConfig(thresholds=(TABLE2_THRESHOLD,)) if table == 2 else EvalConfig()
    out = Path(out_dir)
    body_model = body_model or BodyModel(device=next(detector.parameters()).device)
    textures, records = {}, {}
    for key, (grid_n, parts) in runs.items():
        result = optimize_texture(replace(attack, grid_n=grid_n, parts=parts), detector, out / "runs" / key,
                                  resume=True, body_model=body_model, motions=train_motions, progress=progress)
        textures[key] = (grid_n, parts, np.asarray(result.best_texture, dtype=np.float32))
        records[key] = {"grid_n": grid_n, "parts": list(parts), "steps_this_call": result.steps,
                        "seconds_per_step": None if math.isnan(result.seconds_per_step) else result.seconds_per_step,
                        "best_step": result.best_step,
                        "best_validation_seq_asr": None if math.isnan(result.best_seq_asr) else result.best_seq_asr}
    eval_model = BodyModel()
    if table == 1:
        res = table1({n: grid for n, _, grid in textures.values()}, detector, out, config=eval_config,
                     model=eval_model, parts=PAINTABLE_PARTS, command=command, motions=test_motions,
                     progress=progress)
    else:
        res = table2({"+".join(parts): grid for _, parts, grid in textures.values()}, detector, out,
                     config=eval_config, model=eval_model, command=command, motions=test_motions, progress=progress)
    record = {"table": table, "detector": detector_name, "attack": attack.to_dict(),
              "evaluation": config_dict(eval_config), "runs": records, "load_average": list(os.getloadavg()),
              "command": command}
    path = out / f"reproduce_table{table}.json"
    path.write_text(json.dumps(record, indent=1))
    with open(res["markdown"], "a") as f:
        f.write(_budget_markdown(attack, eval_config, records, detector_name))
    return {**res, "record": path, "runs": records}


def _budget_markdown(attack: AttackConfig, eval_config: EvalConfig, records: dict, detector_name: str | None) -> str:
    lines = ["", "Budget and settings:", "",
             f"- detector: `{detector_name}`" if detector_name else "- detector: (not named)",
             f"- optimize: {attack.iterations} iterations, Adam lr {attack.lr:g}, {attack.clips_per_step} clip(s) per "
             f"step, pool {attack.pool_size} (refresh {attack.refresh_fraction:g} every {attack.refresh_every}), "
             f"alpha schedule {attack.alpha_schedule}"
             + (" (hard part sampled, Bernoulli(u) per cell and step)" if attack.binarize == "sample" else "")
             + f", V2E gradient {attack.v2e_gradient}, anchors "
             + ("all (paper)" if attack.box_margin_px is None else f"within {attack.box_margin_px:g} px of the box")
             + f", loss reduction {attack.loss_reduction}"
             + f", best of validation every {attack.validate_every} steps on {attack.num_validation_clips} clips"
             + (" (by mean top score)" if attack.select_by == "score" else "")
             + (f", then {attack.refine_passes} pass(es) of greedy cell flips scored on {attack.refine_clips} clips"
                if attack.refine_passes else ""),
             f"- evaluation: scales {list(eval_config.scales)}, {len(eval_config.headings_rad)} heading(s), phases "
             f"{list(eval_config.phases)} s, sequences of {eval_config.seq_len} windows, "
             f"{EVENT_MODEL_NAMES[eval_config.events]}", "",
             "| run | best step | best validation SeqASR | s/step (this call) |", "|---|---|---|---|"]
    for key, r in records.items():
        sps = "n/a (finished earlier)" if r["seconds_per_step"] is None else f"{r['seconds_per_step']:.2f}"
        asr = "n/a" if r["best_validation_seq_asr"] is None else f"{100 * r['best_validation_seq_asr']:.1f} %"
        lines.append(f"| {key} | {r['best_step']} | {asr} | {sps} |")
    return "\n".join(lines) + "\n"
