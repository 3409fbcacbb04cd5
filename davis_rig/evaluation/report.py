"""Reports of the physical evaluation: JSON (every number and setting), a markdown table like the paper's Table 3,
a plot of AP and SeqASR vs threshold (matplotlib) and an annotated GIF of event frames with RVT and label boxes
(Pillow). The plot and the GIF need the ``report`` extra (``pip install "davis_rig[report]"``); JSON and the
table need nothing beyond numpy.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import re
from pathlib import Path
from typing import Sequence

import numpy as np

from davis_rig import __version__
from davis_rig.errors import MissingDependencyError

__all__ = ["check_report_dependencies", "gif_file_names", "markdown_table", "report_dict", "write_gif", "write_json",
           "write_plot", "write_report"]


def _pct(value) -> str:
    return "n/a" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{100 * value:.1f}%"


def markdown_table(results, thresholds: Sequence[float] | None = None, *, strict: bool = True) -> str:
    """Table 3 layout: rows (metric, threshold), one column per recording.

    Args:
        results: :class:`~davis_rig.evaluation.physical.RecordingResult` list.
        thresholds: rows to show (default: those of the first result).
        strict: add a row with the strict SeqASR.

    Returns:
        The markdown text (ends with a newline).
    """
    thresholds = list(thresholds or results[0].metrics)
    header = "| Metric | Confidence threshold | " + " | ".join(r.name for r in results) + " |"
    lines = [header, "|---|---|" + "---|" * len(results)]
    for th in thresholds:
        rows = [("AP ↓", "AP"), ("SeqASR ↑", "seq_asr")] + ([("SeqASR strict ↑", "seq_asr_strict")] if strict else [])
        for label, key in rows:
            cells = [_pct(r.metrics[float(th)][key]) for r in results]
            lines.append(f"| {label} | {th:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _clean(obj):
    if isinstance(obj, float) and math.isnan(obj):
        return None
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.generic):
        return _clean(obj.item())
    return obj


def report_dict(results, settings) -> dict:
    """Everything in one JSON-ready dict (NaN written as ``null``)."""
    from davis_rig.evaluation.physical import settings_dict

    return _clean({"format": "davis_rig.physical_evaluation", "toolkit_version": __version__,
                   "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                   "settings": settings_dict(settings), "recordings": [r.as_dict() for r in results]})


def write_json(results, settings, path: Path) -> Path:
    """Write :func:`report_dict` to ``path``."""
    path = Path(path)
    path.write_text(json.dumps(report_dict(results, settings), indent=2, allow_nan=False) + "\n")
    return path


def write_plot(results, path: Path) -> Path:
    """AP and SeqASR (paper and strict) vs confidence threshold, one line per recording (PNG).

    Raises:
        MissingDependencyError: matplotlib is not installed.
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise MissingDependencyError('the plot needs matplotlib: pip install "davis_rig[report]"') from exc
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for r in results:
        ths = sorted(r.metrics)
        axes[0].plot(ths, [100 * r.metrics[t]["AP"] for t in ths], marker="o", label=r.name)
        line = axes[1].plot(ths, [100 * r.metrics[t]["seq_asr"] for t in ths], marker="o", label=f"{r.name} (paper)")
        axes[1].plot(ths, [100 * r.metrics[t]["seq_asr_strict"] for t in ths], marker="x", linestyle="--",
                     color=line[0].get_color(), label=f"{r.name} (strict)")
    for ax, title in zip(axes, ("AP (pedestrian, mAP@[.5:.95]) %", "SeqASR %")):
        ax.set_xscale("log")
        ax.set_xlabel("confidence threshold")
        ax.set_ylim(-3, 103)
        ax.set_title(title)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


def write_gif(scores, threshold: float, path: Path, *, frame_ms: int = 50) -> Path:
    """Annotated GIF: event images (ON bright, OFF dark) with RVT pedestrian boxes (red) and labels (green).

    Args:
        scores: :class:`~davis_rig.evaluation.physical.SessionScores` with ``event_images``.
        threshold: which threshold's detections to draw.
        path: output ``.gif``.
        frame_ms: display time per window, ms.

    Raises:
        MissingDependencyError: Pillow is not installed.
        ValueError: no event images were kept (``gif_windows = 0``).
    """
    try:
        from PIL import Image, ImageDraw
    except ImportError as exc:
        raise MissingDependencyError('the GIF needs Pillow: pip install "davis_rig[report]"') from exc
    from davis_rig.evaluation.physical import label_windows
    from davis_rig.types import PEDESTRIAN_CLASS_ID

    images = scores.event_images
    if len(images) == 0:
        raise ValueError("no event images kept: score with gif_windows > 0")
    labels = scores.labels
    label_win = label_windows(labels, scores.window_end_us, int(scores.window_end_us[1] - scores.window_end_us[0])
                              if len(scores.window_end_us) > 1 else 50_000)
    dets = scores.detections[float(threshold)]
    frames = []
    for i, img in enumerate(images):
        gray = np.clip(128 + 16 * img.astype(np.int32), 0, 255).astype(np.uint8)
        frame = Image.fromarray(gray, mode="L").convert("RGB")
        draw = ImageDraw.Draw(frame)
        for box in labels[label_win == i]:
            draw.rectangle([box["x"], box["y"], box["x"] + box["w"], box["y"] + box["h"]], outline=(0, 220, 0))
        if dets[i] is not None:
            for row in dets[i]:
                if int(row[6]) == PEDESTRIAN_CLASS_ID:
                    draw.rectangle([float(row[0]), float(row[1]), float(row[2]), float(row[3])], outline=(230, 0, 0))
        draw.text((3, 3), f"{(scores.window_end_us[i] - scores.t0_us) / 1e6:.2f} s", fill=(255, 255, 0))
        frames.append(frame)
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=frame_ms, loop=0)
    return Path(path)


def gif_file_names(names: Sequence[str]) -> list[str]:
    """One distinct ``.gif`` file name per recording name (``d1/case`` -> ``d1_case.gif``; clashes get ``-2``...)."""
    out: list[str] = []
    for name in names:
        safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("._") or "recording"
        candidate, n = safe, 1
        while f"{candidate}.gif" in out:
            n += 1
            candidate = f"{safe}-{n}"
        out.append(f"{candidate}.gif")
    return out


def check_report_dependencies(*, plot: bool, gif: bool) -> None:
    """Raise :class:`MissingDependencyError` now (before any scoring) when the plot or the GIF cannot be made."""
    import importlib.util

    for wanted, module, what in ((plot, "matplotlib", "the plot needs matplotlib"),
                                 (gif, "PIL", "the GIF needs Pillow")):
        if wanted and importlib.util.find_spec(module) is None:
            raise MissingDependencyError(f'{what}: pip install "davis_rig[report]" (or leave it out: --no-plot, '
                                         "--gif-seconds 0)")


def write_report(results, scores, settings, out_dir: Path, *, plot: bool = True, gif: bool = True,
                 gif_threshold: float | None = None) -> dict[str, Path]:
    """Write ``report.json``, ``table.md``, ``<name>.detections.npz`` per recording (every window's detections,
    :mod:`davis_rig.evaluation.detections`, for ``davis-view --detections``) and (optionally) ``ap_seqasr.png`` and
    a GIF per recording.

    The files are written into a temporary folder beside ``out_dir`` and moved into ``out_dir`` only when all of
    them are complete, so a failure (or Ctrl-C) leaves ``out_dir`` as it was. GIF names come from
    :func:`gif_file_names` (distinct even when two recordings share a file name).

    Returns:
        ``{kind: path}`` of the written files (``gif:<recording name>`` for the GIFs).

    Raises:
        MissingDependencyError: ``plot``/``gif`` requested without matplotlib/Pillow.
        OSError: ``out_dir`` cannot be created or written.
    """
    import shutil
    import tempfile

    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".partial", dir=out_dir.parent))
    try:
        written = {"json": write_json(results, settings, staging / "report.json")}
        table = staging / "table.md"
        table.write_text(markdown_table(results))
        written["table"] = table
        from davis_rig.evaluation.detections import write_detections

        for r, s, file_name in zip(results, scores, gif_file_names([r.name for r in results])):
            written[f"detections:{r.name}"] = write_detections(
                s, r.name, settings.window_us, staging / f"{file_name[:-len('.gif')]}.detections.npz")
        if plot:
            written["plot"] = write_plot(results, staging / "ap_seqasr.png")
        if gif:
            th = float(gif_threshold if gif_threshold is not None else max(settings.thresholds))
            for r, s, file_name in zip(results, scores, gif_file_names([r.name for r in results])):
                if len(s.event_images):
                    written[f"gif:{r.name}"] = write_gif(s, th, staging / file_name)
        out_dir.mkdir(exist_ok=True)
        for kind, path in written.items():
            written[kind] = Path(shutil.move(str(path), str(out_dir / path.name)))
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return written
