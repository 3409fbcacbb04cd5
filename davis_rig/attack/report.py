"""Reporting of the digital evaluation: the paper's Tables 1 and 2, markdown / JSON / plots, event-frame pictures.

- :func:`table1` (white / black / random 60 x 60 baselines vs optimized textures of grid 60 ... 10, all thresholds)
  and :func:`table2` (the 7 body-part combinations at 10 x 10, threshold 0.25): the test scenes of
  :mod:`davis_rig.attack.evaluate` scored with :func:`~davis_rig.attack.evaluate.evaluate_textures`;
- :func:`write_table`: ``<stem>.md`` (all scales and per scale), ``<stem>.json`` (rows and command) and
  ``<stem>.png`` (AP and SeqASR per threshold);
- :func:`write_visualisations`: event frames with the detector's boxes per texture and a GIF of the person walking
  in a texture.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from davis_rig.attack.evaluate import (
    TABLE2_THRESHOLD,
    EvalConfig,
    TextureSpec,
    baseline_textures,
    evaluate_textures,
    evaluation_scenes,
    prepare_scenes,
    texture_video,
)
from davis_rig.attack.scoring import EVENT_MODEL_NAMES, detect_windows
from davis_rig.scene.scene import Motion, SceneSpec
from davis_rig.types import PEDESTRIAN_CLASS_ID

__all__ = ["results_markdown", "table1", "table2", "write_table", "write_visualisations"]

def _fmt(value: float) -> str:
    return "n/a" if value is None or not np.isfinite(value) else f"{100.0 * value:.1f}"


def results_markdown(rows: Sequence[dict], thresholds: Sequence[float], *, scale: str = "all",
                     label: str = "Texture") -> str:
    """A markdown table: one row per texture, AP and SeqASR (%) per threshold, for one scale group."""
    names = list(dict.fromkeys(r["texture"] for r in rows))
    head = f"| {label} | " + " | ".join(f"AP@{t:g} | SeqASR@{t:g}" for t in thresholds) + " |"
    sep = "|---|" + "---|---|" * len(thresholds)
    lines = [head, sep]
    for name in names:
        cells = []
        for t in thresholds:
            r = next((r for r in rows if r["texture"] == name and r["scale"] == scale and
                      math.isclose(r["threshold"], t)), None)
            cells += [_fmt(r["AP"]) if r else "n/a", _fmt(r["SeqASR"]) if r else "n/a"]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _plot(rows: Sequence[dict], thresholds: Sequence[float], path: Path, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r["texture"] for r in rows))
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for name in names:
        sel = [next(r for r in rows if r["texture"] == name and r["scale"] == "all" and math.isclose(r["threshold"], t))
               for t in thresholds]
        for ax, key in zip(axes, ("AP", "SeqASR")):
            ax.plot(range(len(thresholds)), [100 * s[key] for s in sel], marker="o", label=name)
    for ax, key in zip(axes, ("AP (%)", "SeqASR (%)")):
        ax.set_xticks(range(len(thresholds)), [f"{t:g}" for t in thresholds])
        ax.set_xlabel("confidence threshold")
        ax.set_ylabel(key)
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_table(rows: Sequence[dict], thresholds: Sequence[float], out_dir: str | Path, stem: str, title: str, *,
                command: str | None = None, label: str = "Texture") -> dict:
    """Write ``<stem>.md`` (all scales + per scale), ``<stem>.json`` (rows + command) and ``<stem>.png`` (plots).

    Returns:
        ``{"markdown", "json", "plot": paths, "rows": rows}``.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    text = [f"# {title}\n"]
    if command:
        text.append(f"Command: `{command}`\n")
    text.append("All scales:\n")
    text.append(results_markdown(rows, thresholds, label=label))
    for scale in dict.fromkeys(r["scale"] for r in rows):
        if scale != "all":
            text.append(f"\nScale {scale}:\n")
            text.append(results_markdown(rows, thresholds, scale=scale, label=label))
    md = out_dir / f"{stem}.md"
    md.write_text("\n".join(text))
    js = out_dir / f"{stem}.json"
    js.write_text(json.dumps({"rows": rows, "command": command}, indent=1, default=float))
    png = _plot(rows, thresholds, out_dir / f"{stem}.png", title)
    return {"markdown": md, "json": js, "plot": png, "rows": rows}


def table1(optimized: Mapping[int, np.ndarray], detector, out_dir: str | Path, *, config: EvalConfig | None = None,
           model=None, parts=("torso", "arms", "legs"), command: str | None = None, motions: Sequence[Motion] = (),
           progress: bool = False) -> dict:
    """Table 1: white / black / random 60 x 60 baselines vs optimized textures (grid 60 ... 10), all thresholds.

    Args:
        optimized: grid size n -> float [n, n] optimized texture (e.g. from ``optimize`` runs' ``best_texture.npy``).
        detector: RVT detector.
        out_dir: writes ``table1.md``, ``table1.json``, ``table1.png``.
        config: evaluation settings (default :class:`EvalConfig`).
        model: :class:`~davis_rig.scene.body.BodyModel` (default: bundled asset).
        parts: painted parts of all textures (paper Table 1: the full body).
        command: the command line recorded in the markdown.
        motions: test motions (default: the test shapes' walk cycles).
        progress: progress bar.

    Returns:
        ``{"markdown", "json", "plot": paths, "rows": list}``.
    """
    from davis_rig.scene.body import BodyModel

    config = config or EvalConfig()
    model = model or BodyModel()
    textures = baseline_textures(tuple(parts) if parts else None, seed=config.seed)
    for n in sorted(optimized, reverse=True):
        grid = np.asarray(optimized[n], dtype=np.float32)
        textures[f"ours {n}x{n}"] = TextureSpec(grid, tuple(parts) if parts else None)
    scenes = prepare_scenes(evaluation_scenes(config, model.num_shapes, motions), model, config, progress=progress)
    rows = evaluate_textures(textures, detector, scenes, config, progress=progress)
    return write_table(rows, config.thresholds, out_dir, "table1",
                       f"Table 1: baselines vs optimized textures (digital, {EVENT_MODEL_NAMES[config.events]})",
                       command=command)


def table2(optimized: Mapping[str, np.ndarray], detector, out_dir: str | Path, *, config: EvalConfig | None = None,
           model=None, command: str | None = None, motions: Sequence[Motion] = (), progress: bool = False) -> dict:
    """Table 2: the 7 body-part combinations at 10 x 10 (threshold 0.25 by default).

    Args:
        optimized: combination key (``"torso"``, ``"torso+arms"``, ... as
            :func:`davis_rig.scene.masks.combination_masks`) -> float [n, n] texture optimized on those parts.
        detector, out_dir, model, command, motions, progress: see :func:`table1`.
        config: evaluation settings (default: :class:`EvalConfig` with thresholds ``(0.25,)``).

    Returns:
        ``{"markdown", "json", "plot", "rows"}`` (files ``table2.*``).
    """
    from davis_rig.scene.body import BodyModel

    config = config or EvalConfig(thresholds=(TABLE2_THRESHOLD,))
    model = model or BodyModel()
    textures = {key: TextureSpec(np.asarray(grid, dtype=np.float32), tuple(key.split("+")))
                for key, grid in optimized.items()}
    scenes = prepare_scenes(evaluation_scenes(config, model.num_shapes, motions), model, config, progress=progress)
    rows = evaluate_textures(textures, detector, scenes, config, progress=progress)
    return write_table(rows, config.thresholds, out_dir, "table2",
                       f"Table 2: body-part combinations (10x10, {EVENT_MODEL_NAMES[config.events]})",
                       command=command, label="Parts")


def _event_image(hist: np.ndarray) -> np.ndarray:
    """RGB uint8 [H, W, 3] of one window's histogram [20, H, W]: white background, ON blue, OFF red."""
    on = hist[10:].sum(0).astype(np.float32)
    off = hist[:10].sum(0).astype(np.float32)
    img = np.full(on.shape + (3,), 255, dtype=np.uint8)
    img[off > 0] = (220, 40, 40)
    img[on > 0] = (40, 60, 220)
    img[(on > 0) & (off > 0)] = (120, 0, 120)
    return img


def write_visualisations(textures: Mapping[str, TextureSpec], detector, out_dir: str | Path, *,
                         config: EvalConfig | None = None, model=None, scene_spec: SceneSpec | None = None,
                         threshold: float = TABLE2_THRESHOLD, gif_texture: str | None = None) -> dict:
    """Event frames with the detector's boxes for each texture, and a GIF of the person walking in one texture.

    Args:
        textures: name -> :class:`TextureSpec`.
        detector: RVT detector.
        out_dir: writes ``events_<name>.png`` (one row of the windows per texture) and ``walk_<name>.gif``.
        config: evaluation settings.
        model: body model (default bundled).
        scene_spec: the scene (default: the first test shape, walking right, middle scale).
        threshold: confidence threshold of the drawn boxes.
        gif_texture: texture of the GIF (default: the last one).

    Returns:
        ``{"frames": [paths], "gif": path}``.
    """
    import cv2
    from PIL import Image

    from davis_rig.models.rvt.postprocess import postprocess
    from davis_rig.scene.body import BodyModel

    config = config or EvalConfig()
    model = model or BodyModel()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if scene_spec is None:
        scene_spec = evaluation_scenes(EvalConfig(**{**_config_kwargs(config), "scales": ("middle",),
                                               "headings_rad": (math.pi / 2,), "phases": (0.0,)}),
                                 model.num_shapes)[0][1]
    scene = prepare_scenes([("middle", scene_spec)], model, config)[0]
    frames, masks = [], {}
    for name, texture in textures.items():
        video = texture_video(scene, texture, masks)
        decoded, hist = detect_windows(detector, video, scene.t_us, scene.window_end_us, config.simulator,
                                       events=config.events, window_us=config.window_us)
        dets = postprocess(np.stack(decoded), float(threshold), config.nms_threshold)
        tiles = []
        for k in range(hist.shape[0]):
            img = np.ascontiguousarray(_event_image(hist[k]))
            if np.isfinite(scene.boxes[k]).all():
                x0, y0, x1, y1 = scene.boxes[k].astype(int)
                cv2.rectangle(img, (int(x0), int(y0)), (int(x1), int(y1)), (0, 160, 0), 1)
            for det in (dets[k] if dets[k] is not None else []):
                if int(det[6]) == PEDESTRIAN_CLASS_ID:
                    cv2.rectangle(img, (int(det[0]), int(det[1])), (int(det[2]), int(det[3])), (255, 140, 0), 2)
            tiles.append(img)
        strip = np.concatenate(tiles, axis=1)
        safe = "".join(c if c.isalnum() else "_" for c in name)
        path = out / f"events_{safe}.png"
        cv2.imwrite(str(path), strip[..., ::-1])
        frames.append(path)
    gif_name = gif_texture or list(textures)[-1]
    video = texture_video(scene, textures[gif_name], masks).clamp(0, 1).cpu().numpy()
    images = [Image.fromarray((np.power(f, 1 / 2.2) * 255).astype(np.uint8)) for f in video]
    gif = out / f"walk_{''.join(c if c.isalnum() else '_' for c in gif_name)}.gif"
    images[0].save(gif, save_all=True, append_images=images[1:], duration=int(1000 / 25), loop=0)
    return {"frames": frames, "gif": gif}


def _config_kwargs(config: EvalConfig) -> dict:
    return {f: getattr(config, f) for f in config.__dataclass_fields__}
