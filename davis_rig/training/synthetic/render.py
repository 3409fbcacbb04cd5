"""A synthetic scene → RVT training data: pose → rasterize → compose → simulate → histogram → label.

:func:`render_sequence` turns a :class:`~.scenes.SyntheticScene` into a :class:`SyntheticSequence`, chunk by chunk
of frames (memory bounded by ``chunk_frames``; the results do not depend on it):

1. **pose** — every person is posed by :class:`~davis_rig.scene.body.BodyModel` from a cyclic
   :class:`~davis_rig.scene.motion.Motion` (:func:`person_motion`), the path centred so the person passes
   ``(x_mid_m, depth_mid_m)`` at mid-clip, heading about the vertical axis;
2. **rasterize** — all people of a frame are one mesh (faces offset per person), rasterized by
   :func:`~davis_rig.scene.renderer.rasterize_mesh`, so the z-buffer resolves who occludes whom and every covered
   sample belongs to exactly one person (``face // faces_per_body``);
3. **compose** — per person its clothing texture (:func:`~.paint.clothing_texture`) sampled at its samples, over
   the background (warped per frame when the camera moves, :func:`~davis_rig.scene.background.warp_background`),
   the back distractors and the cars; the front distractors on top;
4. **simulate** — :class:`~davis_rig.events.simulator.EventSimulator` (exact, stateful over the chunks);
5. **histogram** — :func:`~davis_rig.events.histogram.stacked_histograms` of back-to-back 50 ms windows;
6. **label** — at each window end, the tight box of each object's visible coverage (:func:`_label_chunk`), kept
   by :func:`_window_labels`.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from davis_rig._lazy import optional_import
from davis_rig.errors import ShapeError
from davis_rig.events.histogram import WINDOW_US, regular_window_ends, stacked_histograms
from davis_rig.events.simulator import EventSimulator
from davis_rig.scene.background import random_background, warp_background
from davis_rig.scene.camera import PinholeCamera, look_at
from davis_rig.scene.motion import rotation_about_z
from davis_rig.training.synthetic.paint import clothing_texture, distractor_layers, vehicle_layers
from davis_rig.training.synthetic.scenes import PersonSpec, SyntheticScene
from davis_rig.types import BBOX_DTYPE, CAR_CLASS_ID, EVENT_DTYPE, PEDESTRIAN_CLASS_ID, RVT_HW

__all__ = ["STAGES", "SyntheticSequence", "person_motion", "render_sequence"]

#: The timed stages of :func:`render_sequence` (keys of :attr:`SyntheticSequence.timings_s`).
STAGES = ("pose", "rasterize", "compose", "simulate", "histogram", "label")
#: UV texel resolution the lookups use (the body's UV map, as the attack code).
_UV_SIZE = 1024


def person_motion(person: PersonSpec, asset):
    """The cyclic :class:`~davis_rig.scene.motion.Motion` of a person (bundled walk cycle or generated gait).

    Args:
        person: the person.
        asset: :class:`~davis_rig.scene.body.BodyAsset`.

    Returns:
        A cyclic motion (``cycle_advance_m`` set), facing and advancing towards -Y.
    """
    from davis_rig.scene.gait import GaitParams, generate_gait
    from davis_rig.scene.motion import Motion

    if person.motion == "walk_cycle":
        return Motion.from_walk_cycle(asset, person.shape_index, advance=True)
    params = GaitParams(speed_m_s=person.speed_m_s, run=person.run, arm_swing_deg=person.arm_swing_deg,
                        variation=person.gait_variation, seed=int(person.gait_seed % (1 << 32)))
    return generate_gait(params, asset, person.shape_index, fps_hz=200.0)


@dataclass
class SyntheticSequence:
    """One rendered sequence, ready for :meth:`~davis_rig.training.dataset.DatasetWriter.add_sequence`.

    Attributes:
        histograms: uint8 [T, 20, 240, 304], RVT stacked histograms of back-to-back 50 ms windows.
        window_end_us: int64 [T], window end times (µs).
        labels: T BBOX_DTYPE arrays (pedestrian and car boxes at the window end; empty = nothing visible).
        events: the simulated events (EVENT_DTYPE [N]) or ``None`` when not kept.
        object_boxes: float32 [T, P + V, 4] unfiltered visible boxes ``(x0, y0, x1, y1)`` per window and object,
            the P people first, then the V cars (NaN: not visible); visible_px: float32 [T, P + V], visible
            coverage (px) per window and object; object_classes: int64 [P + V], their Gen1 class ids.
        timings_s: wall time per stage (:data:`STAGES`: pose, rasterize, compose, simulate, histogram, label), s.
        meta: JSON-able description (the scene, counts).
    """

    histograms: np.ndarray
    window_end_us: np.ndarray
    labels: list[np.ndarray]
    events: np.ndarray | None
    object_boxes: np.ndarray
    visible_px: np.ndarray
    object_classes: np.ndarray
    timings_s: dict[str, float]
    meta: dict[str, Any] = field(default_factory=dict)


class _StageClock:
    """Wall time per stage (s): ``with clock.stage("pose"): ...`` adds the block's time to ``seconds["pose"]``."""

    def __init__(self) -> None:
        self.seconds = dict.fromkeys(STAGES, 0.0)

    @contextlib.contextmanager
    def stage(self, name: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] += time.perf_counter() - start


def _camera_extrinsics(scene: SyntheticScene, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame world->camera extrinsics: camera at the origin looking along +Y, ego-motion applied."""
    h = scene.camera_height_m
    rotation, translation = look_at([0.0, 0.0, h], [0.0, 1.0, h])
    if scene.ego_motion is not None:
        return scene.ego_motion.apply(rotation, translation, t_s)
    n = len(t_s)
    return np.broadcast_to(rotation, (n, 3, 3)).copy(), np.broadcast_to(translation, (n, 3)).copy()


def _window_grid(scene: SyntheticScene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame times int64 [T] (µs), window ends int64 [W] (µs) and the frame index of each window end [W].

    Raises:
        ShapeError: the scene's frames are not a multiple of the 50 ms window.
    """
    t_us = scene.frame_times_us()
    frame_us = int(round(1e6 / scene.render_rate_hz))
    if WINDOW_US % frame_us:
        raise ShapeError(f"render_rate_hz {scene.render_rate_hz}: the 50 ms window must be a whole number of frames")
    ends = regular_window_ends(0, int(t_us[-1]))
    return t_us, ends, np.searchsorted(t_us, ends)


@dataclass
class _Crowd:
    """The people of a scene as one mesh: motions, clothing textures, mid-clip anchors, merged faces and UVs.

    Attributes:
        people: the people; motions: their cyclic motions; textures: float32 tensors [n, n], their clothing.
        anchors: float64 [P, 3], each motion's root at mid-clip (subtracted so the path passes the mid point).
        faces: int tensor [P F, 3], every person's faces, vertex indices offset by ``k V``; uvs: [P F, 3, 2].
        faces_per_body: F (a sample of face ``f`` belongs to person ``f // F``).
    """

    people: tuple[PersonSpec, ...]
    motions: list
    textures: list
    anchors: list
    faces: Any
    uvs: Any
    faces_per_body: int


def _crowd(scene: SyntheticScene, model, t_s: np.ndarray) -> _Crowd:
    """Motions, textures and mid-clip anchors of the scene's people and their merged mesh (pose set-up)."""
    torch = optional_import("torch", "synthetic data generation")
    from davis_rig.scene.motion import sample as sample_motion

    motions = [person_motion(p, model.asset) for p in scene.people]
    textures = [torch.as_tensor(clothing_texture(p.clothing, p.clothing_seed), device=model.device)
                for p in scene.people]
    t_mid = 0.5 * t_s[-1]
    anchors = []
    for p, m in zip(scene.people, motions):
        _, mid_root = sample_motion(m, np.array([p.motion_start_s + t_mid]))
        anchors.append(mid_root[0].astype(np.float64))
    n_people = len(scene.people)
    n_verts = int(model.rest_vertices(0).shape[0])
    faces = torch.cat([model.faces + k * n_verts for k in range(n_people)]) if n_people else None
    uvs = model.face_uvs.repeat(n_people, 1, 1) if n_people else None
    return _Crowd(scene.people, motions, textures, anchors, faces, uvs, int(model.faces.shape[0]))


def _pose_crowd(crowd: _Crowd, model, t_s: np.ndarray):
    """World vertices of all people at the frame times ``t_s`` [n] (s), float tensor [n, P V, 3]."""
    torch = optional_import("torch", "synthetic data generation")
    from davis_rig.scene.motion import sample as sample_motion

    dev = model.device
    verts = []
    for p, m, anchor in zip(crowd.people, crowd.motions, crowd.anchors):
        rot, root = sample_motion(m, t_s + p.motion_start_s)
        root = root.astype(np.float64)
        root[:, :2] -= anchor[:2]
        v = model.pose(p.shape_index, torch.as_tensor(rot, device=dev),
                       torch.as_tensor(root.astype(np.float32), device=dev))
        rz = torch.as_tensor(rotation_about_z(p.heading_rad), dtype=v.dtype, device=dev)
        offset = torch.tensor([p.x_mid_m, p.depth_mid_m, 0.0], dtype=v.dtype, device=dev)
        verts.append(v @ rz.T + offset)
    return torch.cat(verts, dim=1)


def _textured_people(crowd: _Crowd, raster, background, n: int, hw: tuple[int, int], supersample: int):
    """The people's textures composed over ``background`` [n, H, W], and each person's coverage.

    Returns:
        ``(video float tensor [n, H, W], coverage per person: float32 tensors [n, H, W] in pixels' fractions)``.
    """
    torch = optional_import("torch", "synthetic data generation")
    from davis_rig.scene.texture import prepare_lookup

    owner = torch.div(raster.face, crowd.faces_per_body, rounding_mode="floor")
    values = torch.zeros_like(raster.shade)
    covs = []
    for k, tex in enumerate(crowd.textures):
        sel = torch.nonzero(owner == k).squeeze(1)
        lookup = prepare_lookup(raster.uv.index_select(0, sel), size=_UV_SIZE, grid_n=tex.shape[-1])
        values[sel] = lookup.sample(tex).to(values.dtype)
        count = torch.bincount(raster.sample_pixel.index_select(0, sel), minlength=n * hw[0] * hw[1])
        covs.append(count.view(n, *hw).to(torch.float32) / float(supersample**2))
    return raster.compose(values, background), covs


def _label_chunk(local: np.ndarray, front_alpha: np.ndarray, covs, cars, hw: tuple[int, int]):
    """Visible boxes and visible coverage of every object at the chunk's window-end frames ``local`` [K].

    A person shows where it wins the z-buffer, times ``1 - alpha`` of the front distractors; a car where no later
    car, no person and no front distractor covers it.

    Returns:
        ``(boxes float32 [K, P + V, 4] (x0, y0, x1, y1), NaN: not visible; visible_px float32 [K, P + V])``.
    """
    torch = optional_import("torch", "synthetic data generation")
    from davis_rig.scene.renderer import boxes_from_coverage

    num_people = len(covs or ())
    boxes = np.full((len(local), num_people + len(cars), 4), np.nan, dtype=np.float32)
    visible_px = np.zeros((len(local), num_people + len(cars)), dtype=np.float32)
    visible_front = 1.0 - front_alpha[local]
    people_cov = np.zeros((len(local), *hw), dtype=np.float32)
    for k, cov in enumerate(covs or ()):
        cov_k = cov[torch.as_tensor(local, device=cov.device)].cpu().numpy()
        people_cov += cov_k
        vis = cov_k * visible_front
        boxes[:, k] = boxes_from_coverage(vis)
        visible_px[:, k] = vis.sum(axis=(1, 2))
    visible_car = visible_front * np.clip(1.0 - people_cov, 0.0, 1.0)
    for k in reversed(range(len(cars))):
        car_a = cars[k][0][local]
        vis = car_a * visible_car
        boxes[:, num_people + k] = boxes_from_coverage(vis)
        visible_px[:, num_people + k] = vis.sum(axis=(1, 2))
        visible_car = visible_car * (1.0 - car_a)
    return boxes, visible_px


def _window_labels(ends: np.ndarray, object_boxes: np.ndarray, visible_px: np.ndarray, object_classes: np.ndarray,
                   min_visible_px: float, label_filter: bool) -> list[np.ndarray]:
    """BBOX_DTYPE labels per window: the visible boxes with enough coverage (and, with ``label_filter``, the
    Prophesee / RVT Gen1 box size), ``track_id`` = object index."""
    from davis_rig.metrics.ap import MIN_DIAG_PX, MIN_SIDE_PX

    labels = []
    for i, end in enumerate(ends):
        b = object_boxes[i]
        w = b[:, 2] - b[:, 0]
        h = b[:, 3] - b[:, 1]
        keep = np.isfinite(b).all(axis=1) & (visible_px[i] >= min_visible_px)
        if label_filter:
            keep &= (w * w + h * h >= MIN_DIAG_PX**2) & (w >= MIN_SIDE_PX) & (h >= MIN_SIDE_PX)
        rows = np.nonzero(keep)[0]
        out = np.zeros(len(rows), dtype=BBOX_DTYPE)
        out["t"] = end
        out["x"], out["y"] = b[rows, 0], b[rows, 1]
        out["w"], out["h"] = w[rows], h[rows]
        out["class_id"] = object_classes[rows]
        out["class_confidence"] = 1.0
        out["track_id"] = rows
        labels.append(out)
    return labels


class _ChunkRenderer:
    """The per-chunk steps of :func:`render_sequence` over one scene (state: the simulator, the labels so far)."""

    def __init__(self, scene: SyntheticScene, model, supersample: int, clock: _StageClock):
        self.scene, self.model, self.supersample, self.clock = scene, model, supersample, clock
        self.camera = PinholeCamera.rvt_crop()
        self.hw = self.camera.hw
        if self.hw != tuple(RVT_HW):
            raise ShapeError(f"camera: expected the RVT frame {RVT_HW}, got {self.hw}")
        self.t_us, self.ends, self.label_frames = _window_grid(scene)
        self.t_s = self.t_us / 1e6
        with clock.stage("pose"):
            self.crowd = _crowd(scene, model, self.t_s)
        self.background = random_background(self.hw, np.random.default_rng(scene.background_seed))
        self.rotation, self.translation = _camera_extrinsics(scene, self.t_s)
        self.sim = EventSimulator(self.hw[0], self.hw[1], scene.simulator, device=model.device)
        self.event_pieces: list[np.ndarray] = []
        num_people, num_cars = len(scene.people), len(scene.vehicles)
        self.object_classes = np.array([PEDESTRIAN_CLASS_ID] * num_people + [CAR_CLASS_ID] * num_cars, np.int64)
        self.object_boxes = np.full((len(self.ends), num_people + num_cars, 4), np.nan, dtype=np.float32)
        self.visible_px = np.zeros((len(self.ends), num_people + num_cars), dtype=np.float32)

    def backdrop(self, idx: np.ndarray):
        """Background (warped when the camera moves), back distractors and cars of frames ``idx``.

        Returns:
            ``(backdrop float32 tensor [n, H, W], front distractor layer (alpha, value), car layers)``.
        """
        torch = optional_import("torch", "synthetic data generation")
        scene = self.scene
        if scene.ego_motion is not None:
            bg = warp_background(self.background, self.camera, self.rotation[idx], self.translation[idx],
                                 scene.background_depth_m, (self.rotation[0], self.translation[0]))
        else:
            bg = np.broadcast_to(self.background, (len(idx), *self.hw))
        layers = distractor_layers(scene.distractors, self.t_s[idx], self.hw)
        back_a, back_v = layers["back"]
        bg = bg * (1 - back_a) + back_v
        cars = vehicle_layers(scene.vehicles, self.t_s[idx], self.hw)
        for car_a, car_v in cars:
            bg = bg * (1 - car_a) + car_v
        bg_t = torch.as_tensor(np.ascontiguousarray(bg, dtype=np.float32), device=self.model.device)
        return bg_t, layers["front"], cars

    def people(self, idx: np.ndarray, backdrop):
        """Pose, rasterize and texture the people of frames ``idx`` over ``backdrop``: ``(video, coverages)``."""
        torch = optional_import("torch", "synthetic data generation")
        with self.clock.stage("pose"):
            vertices = _pose_crowd(self.crowd, self.model, self.t_s[idx])
        with self.clock.stage("rasterize"):
            from davis_rig.scene.renderer import rasterize_mesh

            dev = self.model.device
            raster = rasterize_mesh(
                vertices, self.crowd.faces, self.crowd.uvs, self.camera,
                torch.as_tensor(self.rotation[idx], dtype=vertices.dtype, device=dev),
                torch.as_tensor(self.translation[idx], dtype=vertices.dtype, device=dev),
                supersample=self.supersample, light=self.scene.light)
        with self.clock.stage("compose"):
            return _textured_people(self.crowd, raster, backdrop, len(idx), self.hw, self.supersample)

    def render_chunk(self, idx: np.ndarray) -> None:
        """Render, simulate and label the frames ``idx`` (consecutive, after the previous chunk's)."""
        torch = optional_import("torch", "synthetic data generation")
        with self.clock.stage("compose"):
            backdrop, (front_a, front_v), cars = self.backdrop(idx)
        video, covs = self.people(idx, backdrop) if self.scene.people else (backdrop, None)
        with self.clock.stage("compose"):
            if np.any(front_a):
                dev = self.model.device
                fa = torch.as_tensor(front_a, device=dev)
                video = video * (1 - fa.to(video.dtype)) + torch.as_tensor(front_v, device=dev).to(video.dtype)
        with self.clock.stage("simulate"):
            self.event_pieces.append(self.sim.feed(video, self.t_us[idx]))
        with self.clock.stage("label"):
            in_chunk = np.nonzero((self.label_frames >= idx[0]) & (self.label_frames <= idx[-1]))[0]
            if in_chunk.size:
                local = self.label_frames[in_chunk] - idx[0]
                self.object_boxes[in_chunk], self.visible_px[in_chunk] = _label_chunk(local, front_a, covs, cars,
                                                                                       self.hw)

    def events(self) -> np.ndarray:
        """All simulated events so far, EVENT_DTYPE [N] sorted by time."""
        return np.concatenate(self.event_pieces) if self.event_pieces else np.zeros(0, dtype=EVENT_DTYPE)


def render_sequence(scene: SyntheticScene, *, model=None, device: str = "cpu", supersample: int = 2,
                    chunk_frames: int = 40, min_visible_px: float = 40.0, keep_events: bool = False,
                    label_filter: bool = True) -> SyntheticSequence:
    """Render a scene, simulate its events and build RVT histograms and per-window pedestrian labels.

    Args:
        scene: the scene (:func:`~.scenes.sample_scene`, :func:`~.scenes.held_out_scene`).
        model: a :class:`~davis_rig.scene.body.BodyModel` (built from the bundled asset if ``None``).
        device: torch device of rendering and simulation when ``model`` is ``None``.
        supersample: samples per pixel side of the rasterizer.
        chunk_frames: frames rendered per step (bounds memory; results do not depend on it).
        min_visible_px: a person showing less coverage (px) in a window's end frame gets no box.
        keep_events: return the simulated events too.
        label_filter: apply the Prophesee / RVT Gen1 box filter (diag >= 30 px, sides >= 10 px).

    Returns:
        :class:`SyntheticSequence`: ``duration / 50 ms`` windows ending at 50, 100, ... ms.

    Raises:
        ShapeError: the scene's frames are not a multiple of the 50 ms window.
    """
    optional_import("torch", "synthetic data generation")
    from davis_rig.metrics.ap import MIN_DIAG_PX, MIN_SIDE_PX
    from davis_rig.scene.body import BodyModel

    clock = _StageClock()
    model = BodyModel(device=device) if model is None else model
    chunks = _ChunkRenderer(scene, model, supersample, clock)
    for first in range(0, len(chunks.t_us), chunk_frames):
        chunks.render_chunk(np.arange(first, min(first + chunk_frames, len(chunks.t_us))))
    with clock.stage("histogram"):
        events = chunks.events()
        histograms = stacked_histograms(events, chunks.ends)
    labels = _window_labels(chunks.ends, chunks.object_boxes, chunks.visible_px, chunks.object_classes,
                            min_visible_px, label_filter)
    meta = {
        "generator": "davis_rig.training.synthetic",
        "seed": scene.seed,
        "split": scene.split,
        "subset": scene.subset,
        "people": len(scene.people),
        "vehicles": len(scene.vehicles),
        "events": int(events.shape[0]),
        "supersample": supersample,
        "min_visible_px": min_visible_px,
        "label_filter": {"min_diag_px": MIN_DIAG_PX, "min_side_px": MIN_SIDE_PX} if label_filter else None,
        "scene": scene.to_dict(),
    }
    return SyntheticSequence(histograms=histograms, window_end_us=chunks.ends, labels=labels,
                             events=events if keep_events else None, object_boxes=chunks.object_boxes,
                             visible_px=chunks.visible_px, object_classes=chunks.object_classes,
                             timings_s=clock.seconds, meta=meta)
