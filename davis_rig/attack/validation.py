"""Validation of the attack: clips of the training distribution with their own seeds, scored as trained and as tested.

:func:`validation_clips` draws them (the refinement draws its own with another seed offset); :func:`validate`
scores a hard texture on them, as trained (each clip's own sensor, the forward of
:func:`~davis_rig.attack.step.clip_histograms`) and as tested (the evaluation's exact simulator from the ideal
sensor), and :func:`better` ranks the records (:data:`~davis_rig.attack.config.SELECTION_RULES`).
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from davis_rig._lazy import optional_dependency
from davis_rig.attack.config import AttackConfig
from davis_rig.attack.eot import PoolClip, draw_scene, prepare_clip, slot_seed
from davis_rig.attack.scoring import detect_histograms, score_detections, window_histograms
from davis_rig.attack.step import clip_histograms
from davis_rig.stop import check_stop

with optional_dependency("the attack"):
    import torch

__all__ = ["REFINE_SEED_OFFSET", "VALIDATION_BATCH", "VAL_SEED_OFFSET", "better", "validate", "validation_clips"]

#: Offsets added to the run's seed: the validation clips' and the refinement clips' own seeds.
VAL_SEED_OFFSET = 1_000_003
REFINE_SEED_OFFSET = 2_000_003


def validation_clips(config: AttackConfig, model, mask, num: int, seed_offset: int = VAL_SEED_OFFSET,
                     motions: Sequence = (), on_clip: Callable[[], None] | None = None) -> list[PoolClip]:
    """``num`` clips of the training distribution (``motions`` included) with their own seeds (validation or
    refinement, by ``seed_offset``).

    Args:
        config: the attack settings (EoT distribution, grid size, seed).
        model: :class:`~davis_rig.scene.body.BodyModel`.
        mask: bool [1024, 1024] paintable texels, or ``None`` (whole body).
        num: clips to prepare.
        seed_offset: added to ``config.seed``: the validation's or the refinement's own seeds.
        motions: training motions (:func:`~davis_rig.attack.eot.draw_scene`).
        on_clip: called after each prepared clip (progress, stop requests).

    Returns:
        ``num`` :class:`~davis_rig.attack.eot.PoolClip`.
    """
    clips = []
    for i in range(num):
        seed = slot_seed(config.seed + seed_offset, i, 0)
        spec, sensor = draw_scene(config.eot, seed, model.num_shapes, motions)
        clips.append(prepare_clip(spec, sensor, model, config.grid_n, mask, config=config.eot, seed=seed))
        if on_clip is not None:
            on_clip()
    return clips


#: Clips per detector batch in :func:`validate`.
VALIDATION_BATCH = 8


def validate(grid: np.ndarray, clips: Sequence[PoolClip], detector, threshold: float,
             events: str = "exact", *, train_path: tuple[str, str] | None = None, test_path: bool = True,
             stop=None, batch: int = VALIDATION_BATCH) -> dict:
    """Validation SeqASR and top scores of a hard texture on pre-rasterized clips, as tested and as trained.

    The **test path** is the evaluation's: events of the exact simulator (or ``events``) from the ideal sensor
    (:class:`~davis_rig.events.simulator.SimulatorConfig`), simulated on the clip's active box only (the ideal
    sensor is per pixel and nothing changes outside the box: the same histograms as the whole frame). The **training path** (with ``train_path``) is what
    the optimisation sees: the forward of :func:`clip_histograms`, i.e. each clip's own sensor (its threshold,
    per-pixel mismatch and noise events). On a clip drawn with the test sensor both give the same counts. The
    detector runs on ``batch`` clips at once.

    Args:
        grid: float32 [n, n] hard texture.
        clips: validation clips (their lookups carry the part mask).
        detector: RVT detector.
        threshold: confidence threshold.
        events: the event model of the test path (:data:`davis_rig.attack.scoring.EVENT_MODELS`).
        train_path: ``(v2e_mode, v2e_binning)`` of the training (``AttackConfig.v2e_mode``, ``v2e_binning``):
            also score the training path; ``None``: the test path only.
        test_path: score the test path (False needs ``train_path``: the training path alone, half the cost).
        stop: a :class:`~davis_rig.stop.StopOnSignal` polled between clips (internal: a requested stop
            abandons the validation).
        batch: clips per detector call (>= 1).

    Returns:
        ``{"SeqASR", "num_sequences", "num_detected", "mean_top_score"}`` of the test path (top score: mean over
        windows of the highest obj * p_ped); with ``train_path`` also ``"train_SeqASR"``, ``"train_top_score"``
        and, with both paths, ``"transfer_gap"`` = ``mean_top_score - train_top_score`` (> 0: the test detects the
        texture more than training saw).

    Raises:
        ValueError: neither path requested.
    """
    if not test_path and train_path is None:
        raise ValueError("validate needs the test path, the training path or both")
    g = torch.as_tensor(np.asarray(grid, dtype=np.float32), device=clips[0].threshold.device)
    paths = {name: ([], []) for name, wanted in (("test", test_path), ("train", train_path is not None)) if wanted}
    for first in range(0, len(clips), int(batch)):
        chunk = clips[first : first + int(batch)]
        hists = {name: [] for name in paths}
        for clip in chunk:
            check_stop(stop)
            with torch.no_grad():
                if test_path:  # the ideal sensor is per pixel and the video is constant outside the active box
                    y0, y1, x0, x1 = clip.active_box
                    video = clip.active_video(g)
                    crop = torch.as_tensor(window_histograms(video, clip.t_us, clip.window_end_us, events=events,
                                                             device=video.device, window_us=clip.window_us))
                    hist = torch.zeros((*crop.shape[:2], *clip.threshold.shape), dtype=crop.dtype)
                    hist[..., y0:y1, x0:x1] = crop
                    hists["test"].append(hist)
                if train_path is not None:
                    hists["train"].append(clip_histograms(g, clip, train_path[0], train_path[1], gradient="ste"))
        for name, (decoded, tops) in paths.items():
            for dec in detect_histograms(detector, hists[name]):
                decoded.append(dec)
                tops += [float((d[:, 4] * d[:, 6]).max()) for d in dec]
    boxes = [clip.boxes for clip in clips]
    ends = [clip.window_end_us for clip in clips]
    scores = {name: score_detections(decoded, boxes, ends, (threshold,), seq_len=len(clips[0].window_end_us))
              [float(threshold)] for name, (decoded, _) in paths.items()}
    out = {}
    if test_path:
        test = scores["test"]
        out.update(SeqASR=test["SeqASR"], num_sequences=test["num_sequences"], num_detected=test["num_detected"],
                   mean_top_score=float(np.mean(paths["test"][1])))
    if train_path is not None:
        out.update(train_SeqASR=scores["train"]["SeqASR"], train_top_score=float(np.mean(paths["train"][1])))
    if test_path and train_path is not None:
        out["transfer_gap"] = out["mean_top_score"] - out["train_top_score"]
    return out


def _selection_scores(record: dict) -> tuple[float, float]:
    """``(SeqASR, mean top score)`` a validation record is ranked by: the training path's when it has one (the
    validation clips' own sensors, the distribution the texture is trained on), else the test path's."""
    if "train_top_score" in record:
        return record["train_SeqASR"], record["train_top_score"]
    return record["SeqASR"], record["mean_top_score"]


def better(candidate: dict, best: dict | None, select_by: str = "seqasr") -> bool:
    """Whether a validation record beats the best so far under ``select_by``
    (:data:`~davis_rig.attack.config.SELECTION_RULES`), on :func:`_selection_scores`."""
    if best is None:
        return True
    (a, a_top), (b, b_top) = _selection_scores(candidate), _selection_scores(best)
    if select_by == "score":
        return a_top < b_top
    a = -1.0 if not np.isfinite(a) else a
    b = -1.0 if not np.isfinite(b) else b
    return a > b or (a == b and a_top < b_top)
