"""The real-data control: the attack's texture pipeline against a YOLO trained on real images, on APS frames.

Every synthetic-trained RVT resists texture (docs/attack.md), so a failed attack there cannot tell a weak pipeline
from a robust detector. This runs the same texture generator (:class:`~davis_rig.attack.texture.TextureGenerator`,
straight-through binarization), UV part masks, renderer and EoT clip pool (:class:`~davis_rig.attack.eot.ClipPool`,
with the full DAVIS346 camera) against the YOLO the ``davis-label`` labeler runs on APS frames, run in torch
(:class:`~davis_rig.attack_aps.onnx_graph.OnnxGraph`) so that the gradient reaches the texture:

    grid = binarize_ste(generator(), alpha, cut)         [n, n]  cut: 0.5, or Bernoulli cuts (binarize="sample")
    I    = clip.video(grid)[frame]                        [260, 346] linear intensity
    grey = aps_grey(I) (+ read/shot noise, no gradient)   8-bit scale / 255, the ADC of davis_rig.scene.aps
    x    = letterbox(grey) -> [1, 3, 640, 640]            the labeler's pre-processing, bilinear
    p    = max over classes of YOLO(x)                    [8400] person scores
    L    = sum relu(p - conf / 2)                         (davis_rig.controls.bounds.hinge_loss's rule;
                                                          :func:`frame_loss` has the top-anchor variants)

The evaluation (:func:`aps_detection_rates`) does not use this path: it renders held-out scenes (test body shapes,
the evaluation's headings and scales, grey background) into APS frames with :func:`~davis_rig.scene.aps.
synthesize_aps_frames` (shot and read noise, 10-bit ADC) and runs the labeler itself
(:class:`~davis_rig.labelers.yolo.YoloOnnxDetector`, onnxruntime); a frame counts as detected when a box of score
>= conf overlaps the person's visible box with IoU >= 0.5 (the labeler's recall).
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from davis_rig._lazy import optional_dependency
from davis_rig.errors import CheckpointError

with optional_dependency("the APS attack"):
    import torch
    import torch.nn.functional as F

__all__ = ["APS_LOSSES", "ApsAttackConfig", "TorchYolo", "aps_detection_rates", "aps_grey", "aps_pools",
           "aps_scenes", "blended_body", "cell_footprint", "frame_loss", "optimize_aps_texture", "pool_order",
           "shape_blends", "validation_shapes"]

PAD_GREY = 114.0 / 255.0
#: The losses of :func:`frame_loss`.
APS_LOSSES = ("sum", "top", "lse")


def frame_loss(scores: torch.Tensor, conf: float, kind: str = "sum", temperature: float = 0.02) -> torch.Tensor:
    """The attack's loss of a batch of frames' person scores (a scalar, summed over the frames).

    * ``"sum"``: ``sum relu(p - conf / 2)`` over every anchor of every frame (every box above half the threshold);
    * ``"top"``: ``sum_frames relu(max_anchors p - conf / 2)``: only each frame's best anchor (the one the recall
      counts);
    * ``"lse"``: ``sum_frames relu(t * logsumexp(p / t) - conf / 2)``: a soft maximum of temperature ``t``, which
      spreads the gradient over the anchors within about ``t`` of the best one (and bounds the max from above,
      by at most ``t * ln N``).

    Args:
        scores: float tensor [B, N], person score of every anchor of B frames.
        conf: the labeler's confidence threshold (the hinge aims below ``conf / 2``).
        kind: one of :data:`APS_LOSSES`.
        temperature: ``t`` of ``"lse"`` (score units).

    Raises:
        ValueError: unknown ``kind`` or ``temperature <= 0``.
    """
    if kind not in APS_LOSSES:
        raise ValueError(f"unknown APS loss {kind!r}; expected one of {APS_LOSSES}")
    if not temperature > 0:
        raise ValueError(f"temperature must be > 0, got {temperature}")
    if kind == "sum":
        return torch.relu(scores - conf / 2).sum()
    top = scores.amax(dim=1) if kind == "top" else temperature * torch.logsumexp(scores / temperature, dim=1)
    return torch.relu(top - conf / 2).sum()


def pool_order(kind: str, step: int, frames_per_step: int, n_pools: int, rng: np.random.Generator) -> list[int]:
    """The pools (scales) the EoT frames of a step come from.

    ``"random"``: each frame from a pool drawn uniformly (``rng``); ``"cycle"``: frame ``k`` of step ``s`` from pool
    ``(s * frames_per_step + k) % n_pools``, so that every scale gets the same share of frames (exactly, per step,
    when ``frames_per_step`` is a multiple of ``n_pools``).

    Raises:
        ValueError: unknown ``kind``.
    """
    if kind == "random":
        return [int(rng.integers(n_pools)) for _ in range(frames_per_step)]
    if kind == "cycle":
        return [(step * frames_per_step + k) % n_pools for k in range(frames_per_step)]
    raise ValueError(f"unknown scale draw {kind!r}; expected 'random' or 'cycle'")


def aps_grey(intensity: torch.Tensor, config=None) -> torch.Tensor:
    """The labeler's 8-bit grey of an APS frame, / 255, as a differentiable function of the linear intensity.

    The noiseless :func:`davis_rig.scene.aps.to_adc` (``DN = gain * 1023 * min(I * exposure / saturation, 1)
    + offset``, clipped to 0..1023) read as the labeler reads it (:func:`davis_rig.labelers.yolo.to_gray_u8`:
    the top 8 of 16 bits, i.e. ``DN / 4``), without the rounding.

    Args:
        intensity: float tensor [..., H, W], linear intensity.
        config: :class:`~davis_rig.scene.aps.ApsConfig` (default the rig's).

    Returns:
        float tensor [..., H, W] in [0, 1023 / 1020].
    """
    from davis_rig.scene.aps import ADC_MAX_DN, ApsConfig

    config = config or ApsConfig()
    saturation = config.saturation_exposure_us or config.exposure_us
    filled = torch.clamp(intensity * (config.exposure_us / saturation), 0.0, 1.0)
    dn = torch.clamp(config.gain * ADC_MAX_DN * filled + config.offset_dn, 0.0, float(ADC_MAX_DN))
    return dn / 4.0 / 255.0


class TorchYolo(torch.nn.Module):
    """The labeler's YOLO on grey frames, differentiable: letterbox, graph, person score per anchor.

    Args:
        path: the YOLO ``.onnx`` (Ultralytics YOLOv8 layout ``[1, 4 + nc, N]``).
        frame_hw: the frames' (height, width), px.

    Attributes:
        input_hw: the network input (height, width).
    """

    def __init__(self, path, frame_hw: tuple[int, int]):
        super().__init__()
        from davis_rig.attack_aps.onnx_graph import OnnxGraph

        self.graph = OnnxGraph(path)
        imgsz = json.loads(self.graph.metadata.get("imgsz", "[640, 640]"))
        self.input_hw = (int(imgsz[0]), int(imgsz[1]))
        h, w = frame_hw
        gain = min(self.input_hw[0] / h, self.input_hw[1] / w)
        self.resized_hw = (int(round(h * gain)), int(round(w * gain)))
        self.pad_top = (self.input_hw[0] - self.resized_hw[0]) // 2
        self.pad_left = (self.input_hw[1] - self.resized_hw[1]) // 2
        for p in self.parameters():
            p.requires_grad_(False)

    def forward(self, grey: torch.Tensor) -> torch.Tensor:
        """Person score of every anchor: float [B, N] (max over the classes) of grey frames [B, H, W] in [0, 1]."""
        x = F.interpolate(grey[:, None], size=self.resized_hw, mode="bilinear", align_corners=False)
        h, w = self.input_hw
        top, left = self.pad_top, self.pad_left
        x = F.pad(x, (left, w - self.resized_hw[1] - left, top, h - self.resized_hw[0] - top), value=PAD_GREY)
        x = x.expand(-1, 3, -1, -1).contiguous()
        # the export's reshapes fix the batch at 1: one frame at a time
        return torch.cat([self.graph(x[b : b + 1])[:, 4:].amax(dim=1) for b in range(x.shape[0])])


@dataclass(frozen=True)
class ApsAttackConfig:
    """Settings of the APS texture attack.

    Attributes:
        grid_n: texture cells per side; parts: painted parts (``None``: whole body).
        iterations: Adam steps; lr: Adam learning rate of the generator.
        lr_schedule: :data:`~davis_rig.attack.lr_schedule.LR_SCHEDULES`: ``"constant"`` (default, every result
            measured before the option) or ``"cosine_restarts"`` (the attack's default: one cosine from ``lr`` down
            to ``lr_min`` over the run's ``iterations``, so the binary texture stops changing at the end).
        lr_min: the floor of the cosine.
        frames_per_step: EoT frames (one per clip) per step.
        scales: camera scales of the pool (names or person heights in px).
        across_view_probability: share of the EoT clips that walk across the view (heading within 30 degrees of
            +-90; :attr:`~davis_rig.attack.eot.EoTConfig.across_view_probability`), the rest at any heading; 0
            (default): every heading alike.
        shapes: body shapes of the EoT clips (``None``: the training split of
            :func:`~davis_rig.attack.eot.split_shapes`; the tool leaves the validation shapes out of it).
        blend_shapes: in-between bodies added to the EoT clips' shapes (0: none): each blends two of ``shapes``
            at a weight drawn in [0.25, 0.75] (:func:`shape_blends`, :meth:`~davis_rig.scene.body.BodyAsset.
            with_blended_shapes`), so that a texture meets more bodies than the sampled ones it is optimised on.
        pool_size: clips per scale; refresh_every: a quarter of each pool is redrawn every N steps.
        conf: the labeler's confidence threshold (the hinge aims below half of it).
        alpha_schedule: soft-to-hard schedule (:data:`davis_rig.attack.texture.ALPHA_SCHEDULES`).
        binarize: the hard part's cut (:data:`davis_rig.attack.texture.BINARIZERS`): ``"threshold"`` (default, the
            paper's 0.5, every result measured before the option) or ``"sample"`` (uniform per-cell cuts drawn anew
            every step from ``(seed, step)``, :func:`~davis_rig.attack.step.binarization_threshold`: the hard part is
            a Bernoulli(u) grid, so the straight-through gradient is taken at grids sampled around ``u``).
        loss: :func:`frame_loss`'s kind (:data:`APS_LOSSES`); temperature: its ``"lse"`` temperature.
        scale_draw: :func:`pool_order`'s kind: ``"random"`` scale per frame, or ``"cycle"`` (balanced).
        probe_every: steps between probes of the hard texture (0: none): the generator in ``eval()`` mode (no
            dropout), hard-binarized, on a fixed probe of ``probe_clips`` clips per scale drawn apart from the
            training pools (one frame each, fixed noise), its mean top score logged as ``probe_top_score``.
        validate_every: steps between validations of the hard texture (0: none): the ``validate`` callable of
            :func:`optimize_aps_texture` scores it (the labeler's recall on scenes apart from the test's) and the
            best so far is kept as ``best_texture.npy``.
        checkpoint_every: steps between checkpoints; seed: seeds the generator, pool and draws.
    """

    grid_n: int = 60
    parts: tuple[str, ...] | None = ("torso", "arms", "legs")
    iterations: int = 200
    lr: float = 1e-2
    lr_schedule: str = "constant"
    lr_min: float = 1e-7
    frames_per_step: int = 2
    scales: tuple = ("large", "middle", "small")
    across_view_probability: float = 0.0
    shapes: tuple[int, ...] | None = None
    blend_shapes: int = 0
    pool_size: int = 6
    refresh_every: int = 25
    conf: float = 0.25
    alpha_schedule: str = "linear"
    binarize: str = "threshold"
    loss: str = "sum"
    temperature: float = 0.02
    scale_draw: str = "random"
    probe_every: int = 0
    probe_clips: int = 2
    validate_every: int = 0
    checkpoint_every: int = 10
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("grid_n", "iterations", "frames_per_step", "pool_size", "refresh_every", "checkpoint_every",
                     "probe_clips"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.validate_every < 0 or self.blend_shapes < 0:
            raise ValueError(f"validate_every and blend_shapes must be >= 0, got {self.validate_every}, "
                             f"{self.blend_shapes}")
        if not 0 < self.conf < 1 or not self.lr > 0 or not self.temperature > 0 or self.probe_every < 0:
            raise ValueError(f"need 0 < conf < 1, lr > 0, temperature > 0 and probe_every >= 0, got {self.conf}, "
                             f"{self.lr}, {self.temperature}, {self.probe_every}")
        if not 0.0 <= self.across_view_probability <= 1.0:
            raise ValueError(f"across_view_probability must be in [0, 1], got {self.across_view_probability}")
        from davis_rig.attack.lr_schedule import LR_SCHEDULES

        if self.lr_schedule not in LR_SCHEDULES or not 0 <= self.lr_min < self.lr:
            raise ValueError(f"lr_schedule must be one of {LR_SCHEDULES} and 0 <= lr_min < lr, got "
                             f"{self.lr_schedule!r}, {self.lr_min}")
        from davis_rig.attack.texture import BINARIZERS

        if self.binarize not in BINARIZERS:
            raise ValueError(f"binarize must be one of {BINARIZERS}, got {self.binarize!r}")
        if self.loss not in APS_LOSSES or self.scale_draw not in ("random", "cycle"):
            raise ValueError(f"loss must be one of {APS_LOSSES} and scale_draw 'random' or 'cycle', got "
                             f"{self.loss!r}, {self.scale_draw!r}")


def shape_blends(shapes, count: int, seed: int) -> list[tuple[int, int, float]]:
    """``count`` in-between bodies of ``shapes``: ``(a, b, w)`` triples, ``a != b`` drawn uniformly from ``shapes``,
    ``w`` uniform in [0.25, 0.75]; the same ``seed`` draws the same triples.

    Raises:
        ValueError: ``count > 0`` with fewer than two shapes.
    """
    shapes = [int(s) for s in shapes]
    if count > 0 and len(shapes) < 2:
        raise ValueError(f"blending needs at least two shapes, got {shapes}")
    rng = np.random.default_rng([int(seed), 0xB1E4D])
    out = []
    for _ in range(int(count)):
        a, b = rng.choice(len(shapes), size=2, replace=False)
        out.append((shapes[int(a)], shapes[int(b)], float(rng.uniform(0.25, 0.75))))
    return out


def blended_body(config: ApsAttackConfig, body):
    """The body model and config of the EoT clips: ``(body, config)`` as given when ``config.blend_shapes`` is 0,
    else a model of ``body``'s asset with the :func:`shape_blends` of the config's shapes appended and a config
    whose ``shapes`` lists them beside the originals."""
    from dataclasses import replace

    from davis_rig.attack.eot import split_shapes
    from davis_rig.scene.body import BodyModel

    if not config.blend_shapes:
        return body, config
    shapes = tuple(config.shapes) if config.shapes is not None else split_shapes(body.num_shapes)[0]
    blends = shape_blends(shapes, config.blend_shapes, config.seed)
    blended = BodyModel(body.asset.with_blended_shapes(blends), device=body.device, dtype=body.dtype)
    new = tuple(range(body.num_shapes, body.num_shapes + len(blends)))
    return blended, replace(config, shapes=shapes + new)


def aps_pools(config: ApsAttackConfig, body, mask, generations=None, *, probe: bool = False):
    """One EoT clip pool per scale (full DAVIS346 camera); ``generations``: per pool, a checkpoint's slot
    generations (``None``: a new run). ``probe``: the probe's pools instead (``probe_clips`` slots, seeds apart)."""
    from davis_rig.attack.eot import ClipPool, EoTConfig
    from davis_rig.scene.camera import PinholeCamera

    camera = PinholeCamera.davis346()
    generations = generations or [None] * len(config.scales)
    size, offset = (config.probe_clips, 1_000_003) if probe else (config.pool_size, 0)
    return [ClipPool(EoTConfig(camera=camera, scale=s, shapes=config.shapes,
                               across_view_probability=config.across_view_probability),
                     body, config.grid_n, mask, size=size, base_seed=config.seed + offset + 31 * k, generations=gens)
            for k, (s, gens) in enumerate(zip(config.scales, generations))]


class _Probe:
    """The fixed probe of the hard texture: the middle frame of every probe clip, with fixed noise."""

    def __init__(self, config: ApsAttackConfig, body, mask, aps):
        self.aps = aps
        self.seed = config.seed
        self.clips = [(str(pool.config.scale), clip) for pool in aps_pools(config, body, mask, probe=True)
                      for clip in pool.clips.values()]

    @torch.no_grad()
    def scores(self, yolo: "TorchYolo", grid: torch.Tensor) -> dict:
        """``{"probe_top_score": mean top score, "probe_by_scale": {scale: mean top score}}`` of ``grid``."""
        rng = np.random.default_rng([self.seed, 7])
        tops: dict[str, list[float]] = {}
        for scale, clip in self.clips:
            grey = aps_grey(clip.video(grid)[len(clip.t_us) // 2])
            tops.setdefault(scale, []).append(float(yolo((grey + _noise(grey, rng, self.aps))[None]).amax()))
        return {"probe_top_score": float(np.mean([v for vs in tops.values() for v in vs])),
                "probe_by_scale": {s: float(np.mean(v)) for s, v in tops.items()}}


def _noise(grey: torch.Tensor, rng: np.random.Generator, aps) -> torch.Tensor:
    """Shot and read noise of the ADC on the 8-bit / 255 scale (constants: no gradient)."""
    from davis_rig.scene.aps import ADC_MAX_DN

    with torch.no_grad():
        electrons_per_dn = aps.full_well_e / (aps.gain * ADC_MAX_DN)
        dn = torch.clamp(grey * 255.0 * 4.0 - aps.offset_dn, min=0.0)
        std_dn = torch.sqrt(dn / electrons_per_dn + aps.read_noise_dn**2)
        z = torch.from_numpy(rng.standard_normal(tuple(grey.shape)).astype(np.float32)).to(grey.device)
        return z * std_dn / 4.0 / 255.0


def optimize_aps_texture(config: ApsAttackConfig, yolo: TorchYolo, out_dir, *, resume: bool = False, body=None,
                         progress: Callable[[str], None] | None = None,
                         validate: Callable[[np.ndarray], Mapping] | None = None) -> np.ndarray:
    """Optimise a texture against the APS YOLO (see the module docstring); returns the final hard grid [n, n].

    Writes ``out_dir/checkpoint.pt`` (every ``checkpoint_every`` steps; ``resume=True`` continues from it exactly
    as the uninterrupted run would: generator, Adam, pools, the frame draws' and the dropout's random states),
    ``log.jsonl`` (loss, alpha, mean top person score per step; the hard texture's probe scores every
    ``probe_every`` steps, its validation every ``validate_every``) and ``texture.npy`` / ``.png`` (the hard grid);
    with validation, ``best_texture.npy`` / ``.png`` and ``best.json`` (the step, recall and mean top score of
    the best validated texture: lowest recall, then lowest top score).

    Args:
        validate: hard grid [n, n] (0/1) -> ``{"rate": recall, "mean_top_score": ...}`` (an
            :func:`aps_detection_rates` row), called every ``config.validate_every`` steps and after the last.

    Raises:
        CheckpointError: the checkpoint belongs to another configuration.
        ValueError: ``config.validate_every`` without ``validate``.
    """
    import cv2

    from davis_rig.attack.lr_schedule import lr_at
    from davis_rig.attack.step import binarization_threshold
    from davis_rig.attack.texture import TextureGenerator, alpha_at, binarize_ste, hard_binarize
    from davis_rig.scene.aps import ApsConfig
    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.masks import part_mask

    if config.validate_every and validate is None:
        raise ValueError("config.validate_every needs a validate callable")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    body = body or BodyModel()
    mask = part_mask(config.parts) if config.parts is not None else None
    torch.manual_seed(config.seed)
    generator = TextureGenerator(config.grid_n)
    optimizer = torch.optim.Adam(generator.parameters(), lr=config.lr, betas=(0.9, 0.99), weight_decay=1e-5)
    rng = np.random.default_rng(config.seed)
    ckpt = out / "checkpoint.pt"
    start, generations, best, dropout_rng = (_load_checkpoint(ckpt, config, generator, optimizer, rng)
                                             if resume and ckpt.is_file() else (0, None, None, None))
    if best is not None:
        _write_best(out, best)
    clip_body, clip_config = blended_body(config, body)
    pools = aps_pools(clip_config, clip_body, mask, generations)
    aps = ApsConfig()
    probe = _Probe(clip_config, clip_body, mask, aps) if config.probe_every else None
    generator.train()
    if dropout_rng is not None:  # the generator's dropout draws from torch's global generator
        torch.set_rng_state(dropout_rng)
    t0 = time.perf_counter()
    with _log_from(out / "log.jsonl", start).open("a") as log:
        for step in range(start, config.iterations):
            if step and step % config.refresh_every == 0:
                for pool in pools:
                    pool.refresh(step, 0.25)
            alpha = alpha_at(config.alpha_schedule, step, config.iterations)
            lr = lr_at(config.lr_schedule, step, config.lr, config.iterations, config.lr_min)
            for group in optimizer.param_groups:
                group["lr"] = lr
            soft = generator()
            grid = binarize_ste(soft, alpha, binarization_threshold(config.binarize, config.seed, step, soft))
            order = pool_order(config.scale_draw, step, config.frames_per_step, len(pools), rng)
            scores = yolo(torch.stack([_eot_frame(pools[k], grid, rng, aps) for k in order]))
            loss = frame_loss(scores, config.conf, config.loss, config.temperature)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            record = {"step": step + 1, "loss": float(loss.detach()), "alpha": alpha, "lr": lr,
                      "top_score": float(scores.detach().amax(dim=1).mean())}
            if probe is not None and ((step + 1) % config.probe_every == 0 or step + 1 == config.iterations):
                record |= _probed(probe, yolo, generator)
            if config.validate_every and ((step + 1) % config.validate_every == 0 or step + 1 == config.iterations):
                grid_now = _hard_grid(generator)
                row = validate(grid_now)
                record |= {"val_rate": float(row["rate"]), "val_top_score": float(row["mean_top_score"])}
                if best is None or (record["val_rate"], record["val_top_score"]) < (best["rate"],
                                                                                     best["mean_top_score"]):
                    best = {"step": step + 1, "rate": record["val_rate"], "mean_top_score": record["val_top_score"],
                            "texture": grid_now}
                    _write_best(out, best)
            log.write(json.dumps(record) + "\n")
            log.flush()
            if progress is not None:
                probed = f", hard probe {record['probe_top_score']:.3f}" if "probe_top_score" in record else ""
                probed += f", validation recall {record['val_rate']:.3f}" if "val_rate" in record else ""
                progress(f"step {step + 1}/{config.iterations}: loss {record['loss']:.3f}, top score "
                         f"{record['top_score']:.3f}{probed} "
                         f"({(time.perf_counter() - t0) / (step + 1 - start):.1f} s/step)")
            if (step + 1) % config.checkpoint_every == 0 or step + 1 == config.iterations:
                _save_checkpoint(ckpt, config, generator, optimizer, rng, pools, step + 1, best)
    generator.eval()
    with torch.no_grad():
        texture = hard_binarize(generator())
    np.save(out / "texture.npy", texture)
    cv2.imwrite(str(out / "texture.png"), (texture > 0.5).astype(np.uint8) * 255)
    return texture


def _hard_grid(generator) -> np.ndarray:
    """The generator's hard texture [n, n] (``eval()`` mode, no dropout; then back to ``train()``)."""
    from davis_rig.attack.texture import hard_binarize

    generator.eval()
    with torch.no_grad():
        grid = hard_binarize(generator())
    generator.train()
    return grid


def _probed(probe: _Probe, yolo: TorchYolo, generator) -> dict:
    """The probe's scores of the generator's hard texture."""
    return probe.scores(yolo, torch.from_numpy(_hard_grid(generator)))


def _write_best(out: Path, best: dict) -> None:
    """``best_texture.npy`` / ``.png`` and ``best.json`` (step, recall, mean top score) of the best validated grid."""
    import cv2

    np.save(out / "best_texture.npy", best["texture"])
    cv2.imwrite(str(out / "best_texture.png"), (np.asarray(best["texture"]) > 0.5).astype(np.uint8) * 255)
    (out / "best.json").write_text(json.dumps({k: v for k, v in best.items() if k != "texture"}) + "\n")


def cell_footprint(clip, frame: int) -> torch.Tensor:
    """The APS area of every texture cell in one frame of an EoT clip: float [n * n], pixels² (0: not visible).

    A painted covered sample counts ``1 / supersample²`` of its pixel for the cell its (nearest) texel lies in;
    samples outside the part mask count for no cell.

    Args:
        clip: :class:`~davis_rig.attack.eot.PoolClip` (its lookup indexes the n x n grid).
        frame: frame index in ``[0, len(clip.t_us))``.
    """
    y0, y1, x0, x1 = clip.active_box
    here = (clip.active_pixel // ((y1 - y0) * (x1 - x0))) == int(frame)
    painted = clip.lookup.painted[here, 0] > 0
    cells = clip.lookup.index[here, 0][painted]
    n_cells = clip.lookup.texture_hw[0] * clip.lookup.texture_hw[1]
    return torch.bincount(cells, minlength=n_cells).float() / float(clip.raster.supersample**2)


def _eot_frame(pool, grid: torch.Tensor, rng: np.random.Generator, aps) -> torch.Tensor:
    """One APS frame [H, W] (8-bit / 255 scale, noisy) of a random clip of ``pool``, wearing ``grid``."""
    clip = pool.clips[int(pool.owned[int(rng.integers(len(pool.owned)))])]
    grey = aps_grey(clip.video(grid)[int(rng.integers(len(clip.t_us)))])
    return grey + _noise(grey, rng, aps)


def _load_checkpoint(ckpt: Path, config: ApsAttackConfig, generator, optimizer, rng: np.random.Generator):
    """Restore generator, optimizer and rng from ``ckpt``; returns ``(completed steps, pool generations, best
    validated texture record or None, torch's CPU generator state or None)`` (a checkpoint written before the
    torch state was kept has none: its run resumes with other dropout masks than an uninterrupted run's).

    Raises:
        CheckpointError: the checkpoint belongs to another configuration (``iterations`` and ``validate_every``
            may differ; settings added since it was written count as their defaults).
    """
    state = torch.load(ckpt, weights_only=False)
    saved = {k: v for k, v in asdict(ApsAttackConfig()).items() if k not in state["config"]} | state["config"]
    if saved != asdict(config) | {"iterations": saved["iterations"], "validate_every": saved["validate_every"]}:
        raise CheckpointError(f"{ckpt} was written with another configuration")
    generator.load_state_dict(state["generator"])
    optimizer.load_state_dict(state["optimizer"])
    rng.bit_generator.state = state["rng"]
    return int(state["step"]), state["generations"], state.get("best"), state.get("torch_rng")


def _save_checkpoint(ckpt: Path, config: ApsAttackConfig, generator, optimizer, rng: np.random.Generator, pools,
                     step: int, best: dict | None = None) -> None:
    """Write the run state after ``step`` completed steps atomically (temporary file, then rename)."""
    tmp = ckpt.with_suffix(".tmp")
    torch.save({"generator": generator.state_dict(), "optimizer": optimizer.state_dict(), "step": step,
                "rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state(),
                "generations": [p.generations.tolist() for p in pools],
                "config": asdict(config), "best": best}, tmp)
    os.replace(tmp, ckpt)


def _log_from(log_path: Path, start: int) -> Path:
    """Keep the records of ``log_path`` up to step ``start`` (those after a checkpoint are redone); returns it."""
    kept = [line for line in log_path.read_text().splitlines() if json.loads(line)["step"] <= start] if (
        start and log_path.is_file()) else []
    log_path.write_text("".join(line + "\n" for line in kept))
    return log_path


def aps_scenes(eval_config=None, model=None) -> list:
    """Pose and rasterize the scenes of :func:`aps_detection_rates` once (no autograd).

    Args:
        eval_config: :class:`~davis_rig.attack.evaluate.EvalConfig` of the scenes (its camera should be the full
            DAVIS346, :meth:`~davis_rig.scene.camera.PinholeCamera.davis346`; its ``shapes`` ``None``: the test
            split); default the evaluation's scenes with that camera.
        model: :class:`~davis_rig.scene.body.BodyModel`.

    Returns:
        list of :class:`~davis_rig.attack.evaluate.EvalScene`.
    """
    from davis_rig.attack.evaluate import EvalConfig, evaluation_scenes, prepare_scenes
    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.camera import PinholeCamera

    model = model or BodyModel()
    eval_config = eval_config or EvalConfig(camera=PinholeCamera.davis346())
    return prepare_scenes(evaluation_scenes(eval_config, model.num_shapes), model, eval_config)


def validation_shapes(num_shapes: int, count: int = 6) -> tuple[int, ...]:
    """``count`` training-split body shapes spread over the asset (:func:`~davis_rig.attack.eot.split_shapes`):
    the scenes that select a texture never use the test shapes that score it."""
    from davis_rig.attack.eot import split_shapes

    train = split_shapes(num_shapes)[0]
    picks = np.unique(np.linspace(0, len(train) - 1, min(int(count), len(train))).round().astype(int))
    return tuple(int(train[k]) for k in picks)


def aps_detection_rates(textures: Mapping[str, object], labeler, *, eval_config=None, conf: float = 0.25,
                        model=None, aps_config=None, scenes=None) -> list[dict]:
    """The labeler's recall per texture on held-out scenes' APS frames (see the module docstring).

    Args:
        textures: name -> :class:`~davis_rig.attack.evaluate.TextureSpec`.
        labeler: :class:`~davis_rig.labelers.yolo.YoloOnnxDetector` (its own score threshold must be <= conf).
        eval_config, model: the scenes, as :func:`aps_scenes` takes them (ignored when ``scenes`` is given).
        conf: confidence threshold of a detection.
        aps_config: :class:`~davis_rig.scene.aps.ApsConfig` (frame timing, noise).
        scenes: scenes already prepared by :func:`aps_scenes` (repeated scoring prepares them once).

    Returns:
        One row per texture: ``{"texture", "frames", "detected", "rate", "mean_top_score", "by_scale": {scale:
        rate}, "by_heading": {heading in degrees, e.g. "90": rate}}`` (top score: the highest score of a box
        overlapping the person with IoU >= 0.5, 0 if none; heading 0 = towards the camera, ±90 = walking across).
    """
    from davis_rig.attack.evaluate import texture_video
    from davis_rig.metrics.seqasr import box_iou
    from davis_rig.scene.aps import ApsConfig, synthesize_aps_frames

    aps_config = aps_config or ApsConfig()
    scenes = scenes if scenes is not None else aps_scenes(eval_config, model)
    masks: dict = {}
    rows = []
    for name, spec in textures.items():
        found, tops, scales, headings = [], [], [], []
        for index, scene in enumerate(scenes):
            video = texture_video(scene, spec, masks)
            frames = synthesize_aps_frames(video, scene.t_us, _seeded(aps_config, index))
            boxes = scene.raster.boxes()
            for frame in frames:
                mid = (frame.t_start_exposure_us + frame.t_end_exposure_us) // 2
                box = boxes[int(np.argmin(np.abs(scene.t_us - mid)))]
                if not np.isfinite(box).all():
                    continue
                rows_ = labeler.detect(frame.pixels)
                ious = box_iou(rows_[:, :4], box[None].astype(np.float64))[:, 0] if len(rows_) else np.zeros(0)
                hit = ious >= 0.5
                top = float(rows_[hit, 4].max()) if hit.any() else 0.0
                found.append(top >= conf)
                tops.append(top)
                scales.append(str(scene.scale))
                headings.append(f"{math.degrees(scene.spec.heading_rad):g}")
        found = np.asarray(found, bool)
        rows.append({"texture": name, "frames": int(found.size), "detected": int(found.sum()),
                     "rate": float(found.mean()) if found.size else math.nan,
                     "mean_top_score": float(np.mean(tops)) if tops else math.nan,
                     "by_scale": _rate_by(found, scales), "by_heading": _rate_by(found, headings)})
    return rows


def _rate_by(found: np.ndarray, keys: list[str]) -> dict[str, float]:
    """``{key: share of True in found}`` over the frames of each key, keys in first-seen order."""
    keys_array = np.asarray(keys)
    return {key: float(found[keys_array == key].mean()) for key in dict.fromkeys(keys)}


def _seeded(config, index: int):
    from dataclasses import replace

    return replace(config, seed=int(config.seed) * 100_003 + index)

