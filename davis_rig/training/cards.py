"""Model card of a trained detector (markdown), filled from the run's configuration, data card and metrics.

The dataset card is written by :func:`davis_rig.training.dataset.write_dataset_card` (JSON). The model card is
honest by construction: every number comes from the arguments (nothing is filled in when it was not measured,
the entry then reads "not measured").
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping, Sequence

__all__ = ["write_model_card", "render_model_card"]

_LIMITS = """\
- Trained on **synthetic** events only (rendered people, simulated DAVIS346-like events); it was not trained or
  evaluated on Gen1 or on real recordings, and its accuracy there is unknown.
- Gen1 class layout (0 = car, 1 = pedestrian); only the classes present in the training labels are learned.
- Input: 50 ms stacked histograms (20 × 240 × 304, counts clipped at 10), zero-padded to 256 × 320; the
  recurrent state must be carried across windows and reset at the start of a recording.
- The official RVT checkpoints replace this model with one flag where they are available."""


def _fmt(value: Any, digits: int = 3) -> str:
    if value is None:
        return "not measured"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def render_model_card(
    *,
    model_name: str,
    model_config: Mapping[str, Any],
    train_config: Mapping[str, Any],
    dataset_card: Mapping[str, Any] | None = None,
    validation: Mapping[str, Any] | None = None,
    test_metrics: Mapping[str, Mapping[str, Any]] | None = None,
    compute: Mapping[str, Any] | None = None,
    files: Mapping[str, str] | None = None,
    commands: Sequence[str] | None = None,
) -> str:
    """Markdown text of a model card.

    Args:
        model_name: title (e.g. ``"davis_rig RVT-T (synthetic pedestrians)"``).
        model_config: ``RVTConfig.to_dict()``.
        train_config: ``TrainConfig.to_dict()``.
        dataset_card: the dataset card (``dataset_card.json``), or ``None``.
        validation: best validation result (``{"AP", "AP_50", "step"}``) or ``None``.
        test_metrics: per test condition (e.g. clothing × distance) a dict of AP, AP_50, SeqASR... or ``None``.
        compute: what training took (device, steps, hours, ...).
        files: shipped file name → description.
        commands: shell commands that reproduce the model (data, training, evaluation), or ``None``.

    Returns:
        The markdown text.
    """
    lines = [f"# Model card: {model_name}", ""]
    lines += ["## Model", "", f"RVT ({model_config.get('name', 'custom')}) — MaxViT-RNN backbone + YOLOX PAFPN + "
              f"YOLOX head, embed_dim {model_config.get('embed_dim')}, {model_config.get('num_classes')} classes, "
              f"input {model_config.get('in_res_hw')}.", ""]
    if files:
        lines += ["Files:", ""] + [f"- `{name}`: {desc}" for name, desc in files.items()] + [""]
    lines += ["## Data", ""]
    if dataset_card:
        lines.append(f"Dataset `{dataset_card.get('name')}` ({dataset_card.get('layout')}). "
                     f"{dataset_card.get('description', '')}".strip())
        lines.append("")
        lines.append("| split | sequences | windows | labelled frames | boxes | duration (s) |")
        lines.append("|---|---|---|---|---|---|")
        for split, entry in dataset_card.get("splits", {}).items():
            lines.append(f"| {split} | {entry.get('sequences')} | {entry.get('windows')} | "
                         f"{entry.get('labelled_frames')} | {entry.get('boxes')} | {_fmt(entry.get('duration_s'), 1)} |")
    else:
        lines.append("Dataset card: not available.")
    lines += ["", "## Training recipe", ""]
    keys = ("steps", "batch_size", "seq_len", "lr", "weight_decay", "pct_start", "div_factor", "final_div_factor",
            "grad_clip", "precision", "ema_decay", "seed")
    lines += [f"- {k}: `{train_config.get(k)}`" for k in keys if k in train_config]
    if "augment" in train_config:
        lines.append(f"- augmentation: `{json.dumps(train_config['augment'])}`")
    lines += _recipe_lines(train_config)
    lines += ["", "## Compute", ""]
    lines += [f"- {k}: {_fmt(v)}" for k, v in (compute or {}).items()] or ["- not recorded"]
    lines += ["", "## Metrics", "", "COCO mAP@[.5:.95] with the RVT/Prophesee Gen1 protocol (davis_rig.metrics.ap).", ""]
    if validation:
        lines.append(f"- validation (synthetic, step {validation.get('step')}): AP {_fmt(validation.get('AP'))}, "
                     f"AP50 {_fmt(validation.get('AP_50'))}")
    else:
        lines.append("- validation: not measured")
    if test_metrics:
        columns = sorted({k for m in test_metrics.values() for k in m})
        lines += ["", "| condition | " + " | ".join(columns) + " |", "|---|" + "---|" * len(columns)]
        for condition, metrics in test_metrics.items():
            lines.append(f"| {condition} | " + " | ".join(_fmt(metrics.get(c)) for c in columns) + " |")
    else:
        lines.append("- held-out test set: not measured")
    if commands:
        lines += ["", "## Reproduce", "", "```"] + list(commands) + ["```"]
    lines += ["", "## Limits", "", _LIMITS, ""]
    return "\n".join(lines)


def _recipe_lines(train_config: Mapping[str, Any]) -> list[str]:
    """Losses, sampling and stream augmentation as the run's ``train_config`` set them (nothing assumed)."""
    use_l1 = train_config.get("use_l1")
    l1 = {True: " + L1", False: ", no L1"}.get(use_l1, ", L1 not recorded")
    lines = [f"- losses: YOLOX (SimOTA dynamic-k assignment, 5·IoU + objectness BCE + class BCE{l1})"]
    sampling = train_config.get("sampling")
    if sampling == "mixed":
        lines.append("- sampling: truncated BPTT over chunks; half of each batch streams whole sequences with the "
                     "recurrent states carried from chunk to chunk (reset at each sequence start), half are random "
                     "chunks with states reset per chunk (RVT mixed)")
        if "stream_augment" in train_config:
            lines.append(f"- stream augmentation (drawn once per sequence): "
                         f"`{json.dumps(train_config['stream_augment'])}`")
    elif sampling == "random":
        lines.append("- sampling: truncated BPTT over random chunks, states reset per chunk")
    else:
        lines.append(f"- sampling: `{sampling}`" if sampling is not None else "- sampling: not recorded")
    return lines


def write_model_card(path: str | Path, **kwargs: Any) -> Path:
    """Write :func:`render_model_card` (same keyword arguments) to ``path``; returns the path."""
    path = Path(path)
    path.write_text(render_model_card(**kwargs), encoding="utf-8")
    return path
