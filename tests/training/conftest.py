"""Shared fixtures of the training tests: a tiny dataset of moving boxes made of exact event histograms."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.events.histogram import stacked_histograms
from davis_rig.types import BBOX_DTYPE, PEDESTRIAN_CLASS_ID, RVT_HW, make_events

WINDOW_US = 50_000


def moving_box_sequence(seed: int, num_windows: int = 8, num_boxes: int = 1, events_per_window: int = 3000):
    """Events on the edges of rectangles moving horizontally, their exact histograms and per-window labels.

    Returns:
        (histograms uint8 [T, 20, 240, 304], window_end_us int64 [T], labels: T BBOX_DTYPE arrays).
    """
    rng = np.random.default_rng(seed)
    height, width = RVT_HW
    duration_us = num_windows * WINDOW_US
    t = np.sort(rng.integers(0, duration_us, size=events_per_window * num_windows * num_boxes))
    boxes = []
    for _ in range(num_boxes):
        w, h = rng.uniform(30, 60), rng.uniform(60, 110)
        x0, y0 = rng.uniform(10, width - w - 70), rng.uniform(5, height - h - 5)
        v = rng.choice([-1, 1]) * rng.uniform(80, 150) / 1e6  # px per µs
        if v < 0:
            x0 += 60
        boxes.append((x0, y0, w, h, v))
    which = rng.integers(0, num_boxes, size=t.shape[0])
    params = np.array(boxes)[which]
    x_left = params[:, 0] + params[:, 4] * t
    side = rng.integers(0, 4, size=t.shape[0])  # 0 left, 1 right, 2 top, 3 bottom
    u = rng.uniform(0, 1, size=t.shape[0])
    x = np.where(side == 0, x_left, np.where(side == 1, x_left + params[:, 2], x_left + u * params[:, 2]))
    y = np.where(side < 2, params[:, 1] + u * params[:, 3], np.where(side == 2, params[:, 1], params[:, 1] + params[:, 3]))
    leading = (side == 1) == (params[:, 4] > 0)
    p = np.where(side < 2, leading, rng.integers(0, 2, size=t.shape[0])).astype(np.uint8)
    noise = rng.integers(0, 200 * num_windows)
    t = np.concatenate([t, rng.integers(0, duration_us, size=noise)])
    x = np.concatenate([x, rng.uniform(0, width, size=noise)])
    y = np.concatenate([y, rng.uniform(0, height, size=noise)])
    p = np.concatenate([p, rng.integers(0, 2, size=noise)])
    order = np.argsort(t, kind="stable")
    x = np.clip(np.round(x[order]), 0, width - 1).astype(np.uint16)
    y = np.clip(np.round(y[order]), 0, height - 1).astype(np.uint16)
    events = make_events(t[order], x, y, p[order])
    ends = (np.arange(num_windows, dtype=np.int64) + 1) * WINDOW_US
    hist = stacked_histograms(events, ends)
    labels = []
    for end in ends.tolist():
        out = np.zeros(num_boxes, BBOX_DTYPE)
        for i, (bx, by, bw, bh, bv) in enumerate(boxes):
            out[i] = (end, bx + bv * end, by, bw, bh, PEDESTRIAN_CLASS_ID, 1.0, i)
        labels.append(out)
    return hist, ends, labels


def write_moving_boxes(root, *, train: int = 4, val: int = 2, num_windows: int = 8, seed: int = 0):
    """Write a tiny dataset (RVT layout) of moving boxes; returns the root."""
    from davis_rig.training.dataset import DatasetWriter

    with DatasetWriter(root, name="moving-boxes", description="test fixture", compression="lzf") as writer:
        for split, count in (("train", train), ("val", val)):
            for k in range(count):
                s = seed * 1000 + (0 if split == "train" else 500) + k
                hist, ends, labels = moving_box_sequence(s, num_windows, num_boxes=1 + k % 2)
                writer.add_sequence(hist, ends, labels, {"seed": s}, split=split)
    return root


@pytest.fixture(scope="session")
def moving_boxes_dataset(tmp_path_factory):
    """A tiny dataset: 4 train + 2 val sequences of 8 windows each."""
    return write_moving_boxes(tmp_path_factory.mktemp("moving_boxes") / "ds")
