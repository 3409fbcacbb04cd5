"""Test helper: tiny synthetic files in the real AMASS / BVH formats."""

import numpy as np

# A CMU-like BVH skeleton (cmuconvert joint names, Y up, left = +X, T-pose), CMU units (1/0.45 inch).
_JOINTS = [
    # name, parent, offset
    ("Hips", None, (0.0, 17.0, 0.0)),
    ("LHipJoint", "Hips", (0.0, 0.0, 0.0)),
    ("LeftUpLeg", "LHipJoint", (1.6, -1.8, 0.6)),
    ("LeftLeg", "LeftUpLeg", (0.0, -7.2, 0.0)),
    ("LeftFoot", "LeftLeg", (0.0, -7.4, 0.0)),
    ("LeftToeBase", "LeftFoot", (0.0, -0.8, 2.4)),
    ("RHipJoint", "Hips", (0.0, 0.0, 0.0)),
    ("RightUpLeg", "RHipJoint", (-1.6, -1.8, 0.6)),
    ("RightLeg", "RightUpLeg", (0.0, -7.2, 0.0)),
    ("RightFoot", "RightLeg", (0.0, -7.4, 0.0)),
    ("RightToeBase", "RightFoot", (0.0, -0.8, 2.4)),
    ("LowerBack", "Hips", (0.0, 0.4, 0.0)),
    ("Spine", "LowerBack", (0.0, 2.0, 0.0)),
    ("Spine1", "Spine", (0.0, 2.0, 0.0)),
    ("Neck", "Spine1", (0.0, 2.0, 0.0)),
    ("Neck1", "Neck", (0.0, 0.8, 0.0)),
    ("Head", "Neck1", (0.0, 0.8, 0.0)),
    ("LeftShoulder", "Spine1", (0.0, 2.0, 0.0)),
    ("LeftArm", "LeftShoulder", (3.0, 0.0, 0.0)),
    ("LeftForeArm", "LeftArm", (5.0, 0.0, 0.0)),
    ("LeftHand", "LeftForeArm", (4.5, 0.0, 0.0)),
    ("RightShoulder", "Spine1", (0.0, 2.0, 0.0)),
    ("RightArm", "RightShoulder", (-3.0, 0.0, 0.0)),
    ("RightForeArm", "RightArm", (-5.0, 0.0, 0.0)),
    ("RightHand", "RightForeArm", (-4.5, 0.0, 0.0)),
]
_END_SITES = {"LeftToeBase": (0.0, 0.0, 1.0), "RightToeBase": (0.0, 0.0, 1.0), "Head": (0.0, 1.5, 0.0),
              "LeftHand": (1.5, 0.0, 0.0), "RightHand": (-1.5, 0.0, 0.0)}


def write_bvh(path, frames, frame_time_s=1 / 120):
    """Write a BVH with the skeleton above; ``frames``: list of dicts joint -> (z, y, x) degrees, plus 'pos'."""
    children = {}
    for name, parent, _ in _JOINTS:
        children.setdefault(parent, []).append(name)
    offsets = {name: off for name, _, off in _JOINTS}
    lines = ["HIERARCHY"]

    def emit(name, depth):
        pad = "  " * depth
        kind = "ROOT" if depth == 0 else "JOINT"
        lines.append(f"{pad}{kind} {name}")
        lines.append(pad + "{")
        lines.append(f"{pad}  OFFSET " + " ".join(f"{v:.6f}" for v in offsets[name]))
        if depth == 0:
            lines.append(f"{pad}  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation")
        else:
            lines.append(f"{pad}  CHANNELS 3 Zrotation Yrotation Xrotation")
        for child in children.get(name, []):
            emit(child, depth + 1)
        if name in _END_SITES:
            lines.extend([f"{pad}  End Site", pad + "  {",
                          f"{pad}    OFFSET " + " ".join(map(str, _END_SITES[name])), pad + "  }"])
        lines.append(pad + "}")

    emit("Hips", 0)
    order = []

    def walk(name):
        order.append(name)
        for child in children.get(name, []):
            walk(child)

    walk("Hips")
    lines += ["MOTION", f"Frames: {len(frames)}", f"Frame Time: {frame_time_s:.8f}"]
    for frame in frames:
        values = list(frame.get("pos", (0.0, 17.0, 0.0)))
        for name in order:
            values += list(frame.get(name, (0.0, 0.0, 0.0)))
        lines.append(" ".join(f"{v:.6f}" for v in values))
    path.write_text("\n".join(lines) + "\n")
    return path


def write_amass(path, poses, trans, fps=120.0, gender="male"):
    """Write an AMASS-style ``*_poses.npz`` (SMPL-H: poses [T, 156], trans, betas [16], gender, dmpls)."""
    poses = np.asarray(poses, dtype=np.float64)
    np.savez(path, poses=poses, trans=np.asarray(trans, dtype=np.float64), mocap_framerate=np.float64(fps),
             betas=np.zeros(16), gender=np.array(gender), dmpls=np.zeros((len(poses), 8)))
    return path
