"""Pure drawing kernels of the viewer: event and APS images, boxes, the crop outline, panels, encoding.

Every image is RGB uint8 ``[H, W, 3]`` in sensor pixels (origin upper-left, x to the right, y down). Nothing here
mutates its inputs: each function returns a new array. The web page, the live view and the MP4/GIF export all
draw through :func:`render_view`, so what a test checks here is what a user sees.

Pixel conventions (exact, tested):

- event colour: a pixel with more ON than OFF events in the frame is :data:`ON_RGB`, more OFF than ON
  :data:`OFF_RGB`, as many ON as OFF (but some) :data:`ON_RGB`, none :data:`BACKGROUND_RGB`;
- APS grey level: the stored 16-bit value (10-bit ADC << 6) shifted right by 8, i.e. ``value >> 8`` in 0..255;
- a box ``(x1, y1, x2, y2)`` (float px, ``x2``/``y2`` exclusive, as RVT and the labels store them) is drawn as a
  1-px outline on columns ``round(x1)`` and ``round(x2) - 1`` and rows ``round(y1)`` and ``round(y2) - 1``
  (round half up), clipped to the image.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Final

import numpy as np

from davis_rig.errors import ShapeError
from davis_rig.types import DAVIS346_HW, RVT_HW

__all__ = ["LAYERS", "ImageFormat", "ViewContent", "add_event_counts", "aps_image", "box_pixels", "draw_boxes",
           "draw_caption", "draw_outline", "encode_image", "event_counts", "event_image", "render_view", "side_by_side"]

#: Colours, RGB.
BACKGROUND_RGB: Final = (0, 0, 0)
ON_RGB: Final = (255, 255, 255)
OFF_RGB: Final = (64, 128, 255)
LABEL_RGB: Final = (0, 220, 0)
DETECTION_RGB: Final = (255, 40, 40)
CROP_RGB: Final = (255, 200, 0)
GAP_RGB: Final = (40, 40, 40)
CAPTION_RGB: Final = (255, 255, 0)
#: Width of the strip between the event panel and the APS panel, px.
GAP_PX: Final = 4
#: Overlay layers :func:`render_view` knows.
LAYERS: Final = ("events", "aps", "labels", "detections", "crop")


class ImageFormat(StrEnum):
    """Encodings of :func:`encode_image`: PNG (lossless) or JPEG."""

    PNG = "png"
    JPG = "jpg"


def event_counts(x, y, p, hw: tuple[int, int] = DAVIS346_HW) -> np.ndarray:
    """Count the events of each pixel and polarity.

    Args:
        x: columns, integer px [N]. y: rows, integer px [N]. p: polarities {0, 1} [N].
        hw: image (height, width), px.

    Returns:
        int64 ``[2, H, W]``: ``[0]`` OFF counts, ``[1]`` ON counts.

    Raises:
        ShapeError: columns of different lengths, or an event outside the image.
    """
    return np.bincount(_count_cells(x, y, p, hw), minlength=2 * hw[0] * hw[1]).reshape(2, *hw)


def add_event_counts(counts: np.ndarray, x, y, p) -> None:
    """Add the events' counts to ``counts`` in place (a live frame counted chunk by chunk, no copy of the events).

    Args:
        counts: int32 ``[2, H, W]`` OFF/ON counts (as :func:`event_counts`), C-contiguous.
        x, y, p: as :func:`event_counts`.

    Raises:
        ShapeError: as :func:`event_counts`.
    """
    np.add.at(counts.reshape(-1), _count_cells(x, y, p, counts.shape[1:]), np.int32(1))  # same dtype: the fast path


def _count_cells(x, y, p, hw: tuple[int, int]) -> np.ndarray:
    """The cell ``(ON · H + y) · W + x`` (int32) of each event, checked."""
    x, y, p = (np.asarray(v).reshape(-1) for v in (x, y, p))
    if not x.shape == y.shape == p.shape:
        raise ShapeError(f"event columns: expected equal lengths, got x {x.shape}, y {y.shape}, p {p.shape}")
    height, width = hw
    if x.size and (int(x.min()) < 0 or int(x.max()) >= width or int(y.min()) < 0 or int(y.max()) >= height):
        raise ShapeError(f"events outside the {width}x{height} image (w x h): x in [{x.min()}, {x.max()}], "
                         f"y in [{y.min()}, {y.max()}]")
    index = y.astype(np.int32)  # (ON · H + y) · W + x in int32: 2 H W cells fit easily
    index += (p > 0).astype(np.int32) * height
    index *= width
    index += x
    return index


def event_image(counts: np.ndarray) -> np.ndarray:
    """Colour an ``[2, H, W]`` OFF/ON count array (see the module's colour rule).

    Returns:
        uint8 ``[H, W, 3]`` RGB.
    """
    counts = np.asarray(counts)
    if counts.ndim != 3 or counts.shape[0] != 2:
        raise ShapeError(f"counts: expected [2, H, W], got {counts.shape}")
    off, on = counts[0], counts[1]
    palette = np.array([BACKGROUND_RGB, ON_RGB, OFF_RGB], np.uint8)
    # 2: more OFF than ON; else 1 when any ON (ties to ON), 0 when none at all
    return np.take(palette, np.where(off > on, np.uint8(2), (on > 0).view(np.uint8)), axis=0)


def aps_image(pixels: np.ndarray, origin_xy: tuple[int, int] = (0, 0),
              hw: tuple[int, int] = DAVIS346_HW) -> np.ndarray:
    """Grey image of an APS frame's read-out region placed on the sensor (black outside it).

    Args:
        pixels: uint16 ``[h, w]``, libcaer 16-bit scale (10-bit value << 6).
        origin_xy: the region's top-left on the sensor, px.
        hw: sensor (height, width), px.

    Returns:
        uint8 ``[H, W, 3]`` RGB, grey level ``value >> 8``.

    Raises:
        ShapeError: the region does not fit the sensor.
    """
    pixels = np.asarray(pixels)
    if pixels.ndim != 2:
        raise ShapeError(f"APS pixels: expected [rows, cols], got {pixels.shape}")
    x0, y0 = (int(v) for v in origin_xy)
    h, w = pixels.shape
    if x0 < 0 or y0 < 0 or y0 + h > hw[0] or x0 + w > hw[1]:
        raise ShapeError(f"APS region {w}x{h} at ({x0}, {y0}) does not fit the {hw[1]}x{hw[0]} sensor (w x h)")
    image = np.zeros((*hw, 3), np.uint8)
    image[y0:y0 + h, x0:x0 + w] = (pixels.astype(np.uint16) >> 8).astype(np.uint8)[..., None]
    return image


def box_pixels(xyxy) -> np.ndarray:
    """Pixel outline corners of boxes: ``round(x1), round(y1), round(x2) - 1, round(y2) - 1`` (half up).

    Args:
        xyxy: float ``[K, 4]`` boxes (``x2``, ``y2`` exclusive), px.

    Returns:
        int64 ``[K, 4]`` inclusive corners (a box narrower than 1 px keeps ``x2 >= x1``).
    """
    boxes = np.floor(np.asarray(xyxy, np.float64).reshape(-1, 4) + 0.5).astype(np.int64)
    boxes[:, 2:] = np.maximum(boxes[:, 2:] - 1, boxes[:, :2])
    return boxes


def draw_outline(image: np.ndarray, corners, rgb) -> np.ndarray:
    """Draw 1-px rectangle outlines at inclusive pixel corners ``[K, 4]`` (clipped to the image); a new image."""
    out = np.array(image, np.uint8, copy=True)
    height, width = out.shape[:2]
    for x1, y1, x2, y2 in np.asarray(corners, np.int64).reshape(-1, 4).tolist():
        if x2 < 0 or y2 < 0 or x1 >= width or y1 >= height:
            continue
        cx1, cy1, cx2, cy2 = max(x1, 0), max(y1, 0), min(x2, width - 1), min(y2, height - 1)
        for row in (y1, y2):
            if 0 <= row < height:
                out[row, cx1:cx2 + 1] = rgb
        for col in (x1, x2):
            if 0 <= col < width:
                out[cy1:cy2 + 1, col] = rgb
    return out


def _put_text(image: np.ndarray, text: str, xy: tuple[int, int], rgb, scale: float = 0.35) -> None:
    """Draw ``text`` with its baseline-left at ``xy`` in place (cv2 Hershey simplex, 1 px strokes)."""
    import cv2

    cv2.putText(image, text, (int(xy[0]), int(xy[1])), cv2.FONT_HERSHEY_SIMPLEX, scale, tuple(int(c) for c in rgb),
                1, cv2.LINE_8)


def draw_boxes(image: np.ndarray, xyxy, rgb, texts=None, offset_xy: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Draw boxes (and a text above each, e.g. its score) on a copy of ``image``.

    Args:
        image: uint8 ``[H, W, 3]``.
        xyxy: float ``[K, 4]`` boxes, px in the frame whose origin is at ``offset_xy`` on the image (the crop).
        rgb: outline and text colour.
        texts: ``K`` strings or ``None``.
        offset_xy: added to the boxes, px.

    Returns:
        A new uint8 ``[H, W, 3]`` image.
    """
    boxes = np.asarray(xyxy, np.float64).reshape(-1, 4) + np.tile(np.asarray(offset_xy, np.float64), 2)
    corners = box_pixels(boxes)
    out = draw_outline(image, corners, rgb)
    if texts is not None:
        for (x1, y1, _, _), text in zip(corners.tolist(), texts):
            _put_text(out, text, (x1, max(y1 - 2, 8)), rgb)
    return out


def draw_caption(image: np.ndarray, text: str, rgb=CAPTION_RGB) -> np.ndarray:
    """Write a one-line caption at the top-left of a copy of ``image``."""
    out = np.array(image, np.uint8, copy=True)
    _put_text(out, text, (3, 11), rgb)
    return out


def side_by_side(panels, gap_px: int = GAP_PX, gap_rgb=GAP_RGB) -> np.ndarray:
    """Concatenate equally tall ``[H, W_i, 3]`` panels left to right with ``gap_px`` columns of ``gap_rgb``."""
    panels = [np.asarray(panel, np.uint8) for panel in panels]
    heights = {panel.shape[0] for panel in panels}
    if len(heights) != 1:
        raise ShapeError(f"panels: expected one height, got {sorted(heights)}")
    gap = np.empty((heights.pop(), gap_px, 3), np.uint8)
    gap[...] = gap_rgb
    parts = []
    for i, panel in enumerate(panels):
        if i:
            parts.append(gap)
        parts.append(panel)
    return np.concatenate(parts, axis=1)


@dataclass(frozen=True)
class ViewContent:
    """What one displayed frame shows.

    Attributes:
        counts: int ``[2, H, W]`` OFF/ON event counts on the sensor (:func:`event_counts`), or ``None``.
        aps: ``(pixels uint16 [h, w], (x0, y0))`` of the APS frame to show, or ``None``.
        labels_xyxy: float ``[L, 4]`` ground-truth boxes in crop px.
        detections: float32 ``[K, 7]`` RVT rows ``(x1, y1, x2, y2, obj, class_conf, class_id)`` in crop px.
        crop_origin_xy: the 304x240 crop's top-left on the sensor, px.
        layers: which of :data:`LAYERS` to draw.
        caption: text at the top-left of the event panel (``""``: none).
        sensor_hw: sensor (height, width), px.
    """

    counts: np.ndarray | None = None
    aps: tuple | None = None
    labels_xyxy: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    detections: np.ndarray = field(default_factory=lambda: np.zeros((0, 7), np.float32))
    crop_origin_xy: tuple[int, int] = (21, 10)
    layers: frozenset = frozenset(LAYERS)
    caption: str = ""
    sensor_hw: tuple[int, int] = DAVIS346_HW


def _overlays(panel: np.ndarray, content: ViewContent) -> np.ndarray:
    origin = tuple(int(v) for v in content.crop_origin_xy)
    if "crop" in content.layers:
        x0, y0 = origin
        panel = draw_outline(panel, [[x0 - 1, y0 - 1, x0 + RVT_HW[1], y0 + RVT_HW[0]]], CROP_RGB)
    if "labels" in content.layers and len(content.labels_xyxy):
        panel = draw_boxes(panel, content.labels_xyxy, LABEL_RGB, offset_xy=origin)
    if "detections" in content.layers and len(content.detections):
        det = np.asarray(content.detections, np.float32).reshape(-1, 7)
        scores = [f"{s:.2f}" for s in (det[:, 4] * det[:, 5]).tolist()]
        panel = draw_boxes(panel, det[:, :4], DETECTION_RGB, scores, offset_xy=origin)
    return panel


def render_view(content: ViewContent) -> np.ndarray:
    """Draw one displayed frame: the event panel (left) and the APS panel (right), both with the overlays.

    The crop outline runs one pixel outside the 304x240 crop (so it hides no event of it): columns ``x0 - 1`` and
    ``x0 + 304``, rows ``y0 - 1`` and ``y0 + 240``. Labels are drawn before detections (a detection on top of a
    label shows).

    Returns:
        uint8 ``[H, 2 W + GAP_PX, 3]`` RGB.
    """
    height, width = content.sensor_hw
    blank = np.zeros((height, width, 3), np.uint8)
    events = event_image(content.counts) if "events" in content.layers and content.counts is not None else blank
    if "aps" in content.layers and content.aps is not None:
        aps = aps_image(content.aps[0], content.aps[1], content.sensor_hw)
    else:
        aps = blank
    left, right = _overlays(events, content), _overlays(aps, content)
    if content.caption:
        left = draw_caption(left, content.caption)
    return side_by_side([left, right])


def encode_image(image: np.ndarray, fmt: str = ImageFormat.PNG, jpeg_quality: int = 85) -> bytes:
    """Encode an RGB uint8 image as PNG (lossless, compression level 1) or JPEG (4:4:4).

    Args:
        image: uint8 ``[H, W, 3]`` RGB.
        fmt: ``"png"`` or ``"jpg"``.
        jpeg_quality: 0..100, for JPEG.

    Returns:
        The encoded bytes.

    Raises:
        ValueError: unknown format.
    """
    import cv2

    bgr = np.ascontiguousarray(np.asarray(image, np.uint8)[..., ::-1])
    if fmt == ImageFormat.PNG:
        ok, data = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    elif fmt == ImageFormat.JPG:
        # 4:4:4: no chroma subsampling, so 1-px coloured box outlines stay their colour
        ok, data = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality),
                                              cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444])
    else:
        raise ValueError(f"image format: expected {' or '.join(repr(f.value) for f in ImageFormat)}, got {fmt!r}")
    if not ok:  # pragma: no cover - OpenCV fails only on invalid arrays, which the asarray above rules out
        raise ValueError(f"OpenCV could not encode a {image.shape} image as {fmt}")
    return data.tobytes()
