"""Camera intrinsics, look-at extrinsics, test scales, EoT jitter and ego-motion."""

import math

import numpy as np
import pytest
import torch

from davis_rig.errors import ShapeError
from davis_rig.scene.camera import (
    DAVIS346_FOCAL_PX,
    TEST_SCALES_PX,
    EgoMotion,
    EoTJitter,
    PinholeCamera,
    distance_for_height,
    look_at,
    rotation_from_vector,
)


def test_davis346_intrinsics():
    cam = PinholeCamera.davis346()
    assert cam.hw == (260, 346)
    assert cam.fx_px == pytest.approx(12.0 / 0.0185) == pytest.approx(648.6486, abs=1e-3)
    assert (cam.cx_px, cam.cy_px) == (173.0, 130.0)
    crop = PinholeCamera.rvt_crop()
    assert crop.hw == (240, 304)
    assert (crop.cx_px, crop.cy_px) == (152.0, 120.0)  # centred crop at origin (21, 10)
    assert crop.fx_px == cam.fx_px == DAVIS346_FOCAL_PX
    np.testing.assert_allclose(cam.matrix, [[cam.fx_px, 0, 173], [0, cam.fy_px, 130], [0, 0, 1]])
    assert cam.scaled(3).hw == (780, 1038) and cam.scaled(3).cx_px == 519.0


def test_crop_outside_raises():
    with pytest.raises(ShapeError, match="does not fit"):
        PinholeCamera.davis346().crop(50, 0, 304, 240)


def test_look_at_axes_and_projection():
    rotation, translation = look_at([0.0, -5.0, 1.0], [0.0, 0.0, 1.0])
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    cam = PinholeCamera.rvt_crop()
    points = torch.tensor([[[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 0.0, 2.0]]], dtype=torch.float64)
    p = cam.project(points, torch.as_tensor(rotation), torch.as_tensor(translation))[0].numpy()
    np.testing.assert_allclose(p[0], [152.0, 120.0, 5.0], atol=1e-9)  # target -> principal point
    np.testing.assert_allclose(p[1], [152.0 + cam.fx_px / 5.0, 120.0, 5.0], atol=1e-9)  # +X -> image right
    np.testing.assert_allclose(p[2], [152.0, 120.0 - cam.fy_px / 5.0, 5.0], atol=1e-9)  # +Z -> image up


def test_look_at_degenerate():
    with pytest.raises(ValueError):
        look_at([0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError):
        look_at([0, 0, 0], [0, 0, 3])


def test_scales_follow_official_distances():
    assert TEST_SCALES_PX["middle"] == 150.0
    d = {name: distance_for_height(name) for name in TEST_SCALES_PX}
    assert d["large"] / d["middle"] == pytest.approx(1.5 / 1.75)
    assert d["small"] / d["middle"] == pytest.approx(2.0 / 1.75)
    # a fronto-parallel 1.75 m segment at that distance spans exactly the scale's height
    cam = PinholeCamera.rvt_crop()
    for name, height_px in TEST_SCALES_PX.items():
        rotation, translation = look_at([0.0, -d[name], 0.875], [0.0, 0.0, 0.875])
        seg = torch.tensor([[[0.0, 0.0, 0.0], [0.0, 0.0, 1.75]]], dtype=torch.float64)
        p = cam.project(seg, torch.as_tensor(rotation), torch.as_tensor(translation))[0].numpy()
        assert p[0, 1] - p[1, 1] == pytest.approx(height_px)
        assert 0 < p[1, 1] and p[0, 1] < 240  # inside the frame
    with pytest.raises(ValueError):
        distance_for_height("huge")


def test_rotation_from_vector():
    r = rotation_from_vector([0.0, 0.0, math.pi / 2])
    np.testing.assert_allclose(r @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(rotation_from_vector([0.0, 0.0, 0.0]), np.eye(3))


def test_eot_jitter_probabilities_and_ranges():
    rng = np.random.default_rng(0)
    jitter = EoTJitter()
    rotated = scaled = 0
    for _ in range(2000):
        rotation, factor = jitter.sample(rng)
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        angle = math.acos(np.clip((np.trace(rotation) - 1) / 2, -1, 1))
        assert angle <= 0.1 * math.sqrt(3) + 1e-9
        assert 1 - 0.25 / 1.75 <= factor <= 1 + 0.25 / 1.75
        rotated += not np.allclose(rotation, np.eye(3))
        scaled += factor != 1.0
    # p = 0.4 each: 800 expected, sd ~ 22
    assert 700 < rotated < 900 and 700 < scaled < 900
    none = EoTJitter(rotation_probability=0.0, distance_probability=0.0).sample(rng)
    assert np.array_equal(none[0], np.eye(3)) and none[1] == 1.0


def test_ego_motion_starts_at_rest_and_is_smooth():
    rotation, translation = look_at([0.0, -7.0, 0.9], [0.0, 0.0, 0.9])
    ego = EgoMotion(pan_amplitude_rad=0.05, tilt_amplitude_rad=0.02, period_s=1.0, phase_rad=0.3, velocity_m_s=(0.2, 0, 0))
    t_s = np.arange(0, 1, 0.005)
    r, t = ego.apply(rotation, translation, t_s)
    assert r.shape == (200, 3, 3) and t.shape == (200, 3)
    np.testing.assert_allclose(r[0], rotation, atol=1e-12)
    np.testing.assert_allclose(t[0], translation, atol=1e-12)
    centres = -np.einsum("tji,tj->ti", r, t)
    np.testing.assert_allclose(centres[:, 0], 0.2 * t_s, atol=1e-9)  # constant velocity
    step = np.abs(np.diff(r, axis=0)).max()
    assert step < 0.01  # no jumps between 5 ms frames
    r_static, _ = EgoMotion().apply(rotation, translation, t_s)
    np.testing.assert_allclose(r_static, np.broadcast_to(rotation, r_static.shape), atol=1e-12)
    random = EgoMotion.random(np.random.default_rng(1))
    assert abs(random.pan_amplitude_rad) <= 0.05
