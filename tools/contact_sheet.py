"""Contact sheet of synthetic scenes: rendered frames with ground-truth boxes, part labels and event frames.

One row per scene (the three test scales, several headings, backgrounds, lights, EoT jitter and camera
ego-motion, white and grid textures), columns: frames at the start / middle / end of the clip with the
coverage box (green) and the projected-vertex box (yellow), the part-label image of the middle frame, and the
events of the clip's last 50 ms (ON white, OFF black on grey) from :mod:`davis_rig.events.simulator`; when
that module is not importable the event column says so.

Usage::

    python tools/contact_sheet.py --out contact_sheet.png [--grid-n 10] [--seed 0] [--supersample 2] [--duration-ms 200]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

PART_COLOURS_BGR = np.array(
    [[60, 60, 220], [60, 200, 60], [220, 120, 40], [40, 220, 220], [220, 60, 220], [220, 220, 60]], dtype=np.uint8
)


def _to_bgr(image: np.ndarray) -> np.ndarray:
    import cv2

    gray = (np.clip(image, 0.0, 1.0) ** (1 / 2.2) * 255).astype(np.uint8)  # display gamma
    return cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)


def _draw_box(image: np.ndarray, box: np.ndarray, colour) -> None:
    import cv2

    if np.isfinite(box).all():
        x0, y0, x1, y1 = box
        cv2.rectangle(image, (int(math.floor(x0)), int(math.floor(y0))), (int(math.ceil(x1)) - 1, int(math.ceil(y1)) - 1), colour, 1)


def _label(image: np.ndarray, text: str) -> None:
    import cv2

    (width, height), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.4, 1)
    cv2.rectangle(image, (0, 0), (width + 6, height + 7), (30, 30, 30), -1)
    cv2.putText(image, text, (3, height + 3), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)


def _event_frame(clip, hw) -> tuple[np.ndarray, str]:
    """ON/OFF events of the clip's last RVT window (50 ms) on grey, or a note when the simulator is missing."""
    from davis_rig.events.histogram import WINDOW_US

    try:
        from davis_rig.events.simulator import simulate_events
    except ImportError as exc:
        image = np.full(hw + (3,), 128, np.uint8)
        return image, f"no simulator ({exc.name})"
    video = clip.video.detach()
    events = simulate_events(video, clip.t_us)
    t_end = int(clip.t_us[-1])
    recent = events[events["t"] > t_end - WINDOW_US]
    image = np.full(hw + (3,), 128, np.uint8)
    on = recent["p"] == 1
    image[recent["y"][~on], recent["x"][~on]] = 0
    image[recent["y"][on], recent["x"][on]] = 255
    return image, f"events {len(recent)} / {WINDOW_US // 1000} ms"


def build_scenes(grid_n: int, seed: int, supersample: int, duration_s: float = 0.2):
    """The scenes of the sheet: (title, SceneSpec, texture or None, mask or None)."""
    import torch

    from davis_rig.scene.camera import EgoMotion, EoTJitter
    from davis_rig.scene.masks import part_mask
    from davis_rig.scene.scene import SceneSpec

    rng = np.random.default_rng(seed)
    grid = torch.as_tensor((rng.random((grid_n, grid_n)) > 0.5).astype(np.float32))
    mask = part_mask(("torso", "arms", "legs"))
    common = dict(duration_s=duration_s, supersample=supersample)
    always = EoTJitter(rotation_probability=1.0, distance_probability=1.0)
    return [
        ("large, white, walk right", SceneSpec(scale="large", heading_rad=math.pi / 2, **common), None, None),
        ("middle, grid, towards cam", SceneSpec(scale="middle", heading_rad=0.35, background="random", light="random", seed=seed + 1, **common), grid, mask),
        ("small, grid, walk left", SceneSpec(scale="small", heading_rad=-math.pi / 2, background="random", light="random", seed=seed + 2, **common), grid, mask),
        ("middle, grid, EoT jitter", SceneSpec(heading_rad=2.4, background="random", light="random", jitter=always, seed=seed + 3, shape_index=5, **common), grid, mask),
        ("middle, grid, ego-motion", SceneSpec(heading_rad=math.pi / 2, background="random", ego_motion=EgoMotion(pan_amplitude_rad=0.03, period_s=0.4, velocity_m_s=(0.3, 0.0, 0.0)), seed=seed + 4, shape_index=11, **common), grid, mask),
    ]  # fmt: skip


def make_sheet(out: Path, grid_n: int = 10, seed: int = 0, supersample: int = 2, duration_s: float = 0.2) -> Path:
    """Render the scenes and write the sheet PNG; returns its path."""
    import cv2

    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.scene import render_clip

    model = BodyModel()
    rows = []
    for title, spec, texture, mask in build_scenes(grid_n, seed, supersample, duration_s):
        start = time.perf_counter()
        clip = render_clip(spec, texture, model=model, mask=mask, part_labels=True)
        elapsed_ms = (time.perf_counter() - start) * 1e3 / len(clip.t_us)
        video = clip.video.detach().cpu().numpy()
        picks = [0, len(video) // 2, len(video) - 1]
        tiles = []
        for k in picks:
            tile = _to_bgr(video[k])
            _draw_box(tile, clip.vertex_boxes[k], (0, 220, 220))
            _draw_box(tile, clip.boxes[k], (0, 220, 0))
            _label(tile, f"t={clip.t_us[k] / 1000:.0f} ms")
            tiles.append(tile)
        labels = clip.part_labels[picks[1]]
        part_tile = np.zeros(labels.shape + (3,), np.uint8)
        person = labels != 255
        part_tile[person] = PART_COLOURS_BGR[labels[person]]
        _label(part_tile, "part labels")
        tiles.append(part_tile)
        event_tile, note = _event_frame(clip, clip.video.shape[1:])
        _label(event_tile, note)
        tiles.append(event_tile)
        row = np.concatenate([np.pad(t, ((1, 1), (1, 1), (0, 0)), constant_values=40) for t in tiles], axis=1)
        header = np.full((18, row.shape[1], 3), 30, np.uint8)
        cv2.putText(header, title, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        rows.append(np.concatenate([header, row], axis=0))
        print(f"{title}: {len(clip.t_us)} frames, {elapsed_ms:.1f} ms/frame rendered, box[mid]={clip.boxes[picks[1]].tolist()}")
    sheet = np.concatenate(rows, axis=0)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), sheet):
        raise OSError(f"could not write {out}")
    return out


def main(argv=None) -> int:
    """Entry point; returns the exit code."""
    from davis_rig.cli.common import new_parser, non_negative_int, positive_float, positive_int, run_main

    parser = new_parser(Path(__file__).name, __doc__.split("\n\n")[0],
                        "examples:\n  python tools/contact_sheet.py --out contact_sheet.png --grid-n 10\n")
    parser.add_argument("--out", type=Path, default=Path("contact_sheet.png"), help="output PNG")
    parser.add_argument("--grid-n", type=positive_int, default=10,
                        help="n of the random n x n black/white grid texture")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument("--supersample", type=positive_int, default=2, help="samples per pixel side")
    parser.add_argument("--duration-ms", type=positive_float, default=200.0, help="clip length per scene (ms)")
    return run_main(parser, argv, _sheet)


def _sheet(args: argparse.Namespace) -> int:
    path = make_sheet(args.out, args.grid_n, args.seed, args.supersample, args.duration_ms / 1000.0)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
