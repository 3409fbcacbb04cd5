"""davis_rig.scene.gait: normative curve fits, foot contact, walk vs run, heading/turning, seeded variation."""

import math

import numpy as np
import pytest

from davis_rig.scene.gait import (
    FIT_MAX_ERROR_DEG,
    FOURIER_COEFFICIENTS,
    NATIVE_STANCE_FRACTION,
    NORMATIVE_TABLES,
    GaitParams,
    evaluate_fourier,
    fit_fourier,
    generate_gait,
    joint_angles_deg,
)

torch = pytest.importorskip("torch")


@pytest.mark.parametrize("name", sorted(NORMATIVE_TABLES))
def test_stored_coefficients_are_the_fit_of_the_tables(name):
    np.testing.assert_allclose(FOURIER_COEFFICIENTS[name], fit_fourier(NORMATIVE_TABLES[name]), atol=1e-4)
    table = np.asarray(NORMATIVE_TABLES[name], dtype=np.float64)
    error = np.abs(evaluate_fourier(FOURIER_COEFFICIENTS[name], table[:, 0] / 100) - table[:, 1])
    assert error.max() <= FIT_MAX_ERROR_DEG[name] + 0.01
    assert error.max() < 0.5  # within the ±2-3° reading precision of the sources


def test_walk_and_run_curves_at_native_timing():
    p = np.array([0.0, 0.15, 0.62, 0.73])
    walk = joint_angles_deg(p, run=0.0)
    np.testing.assert_allclose(walk["knee"], evaluate_fourier(FOURIER_COEFFICIENTS["walk_knee"], p), atol=1e-9)
    np.testing.assert_allclose(walk["knee"], [5, 18, 40, 60], atol=0.5)  # Perry's knee events
    run = joint_angles_deg(np.array([0.39, 0.70]), run=1.0)
    np.testing.assert_allclose(run["knee"], [18, 95], atol=0.5)  # toe-off and swing peak (Novacheck)
    # toe-off of the blend is aligned: ankle plantarflexion peak at the blended stance end
    s = 0.5 * (NATIVE_STANCE_FRACTION["walk"] + NATIVE_STANCE_FRACTION["run"])
    half = joint_angles_deg(np.array([s]), run=0.5)
    np.testing.assert_allclose(half["ankle"], [0.5 * (-20.0 + -22.0)], atol=1.0)


@pytest.fixture(scope="module")
def sole_sides(asset):
    feet = np.unique(asset.faces[asset.face_parts == asset.part_names.index("feet")])
    x = asset.rest_vertices_m[0, feet, 0]
    return {"L": feet[x > 0], "R": feet[x < 0]}


def _pose(model, motion):
    with torch.no_grad():
        return model.pose(0, torch.as_tensor(motion.rotations_wxyz.copy()),
                          torch.as_tensor(motion.root_translation_m.copy())).double().numpy()


def _contact_stats(vertices, sides, fps):
    low = {s: vertices[:, ids, 2].min(axis=1) for s, ids in sides.items()}
    speeds = []
    for s, o in (("L", "R"), ("R", "L")):
        ids = sides[s]
        single = (low[s] < 1e-3) & (low[o] > 0.01)  # this foot alone on the ground
        pivot = np.argmin(vertices[:, ids, 2], axis=1)
        k = np.flatnonzero(single[:-1] & single[1:])
        step = vertices[k + 1, ids[pivot[k]]] - vertices[k, ids[pivot[k]]]
        speeds.append(np.linalg.norm(step, axis=1) * fps)
    return low, np.concatenate(speeds)


@pytest.fixture(scope="module")
def walk(asset):
    return generate_gait(GaitParams(speed_m_s=1.3), asset, 0)


@pytest.fixture(scope="module")
def run(asset):
    return generate_gait(GaitParams(speed_m_s=3.2, run=1.0), asset, 0)


def test_walk_is_a_cycle_at_the_requested_speed(walk):
    assert walk.is_cycle and walk.fps_hz == pytest.approx(200.0, rel=0.01)
    assert walk.speed_m_s == pytest.approx(1.3, rel=1e-3)
    np.testing.assert_allclose(walk.cycle_advance_m[[0, 2]], 0.0, atol=1e-9)  # straight, towards -Y
    assert walk.cycle_advance_m[1] < 0
    assert 100 < walk.metadata["cadence_steps_min"] < 130 and walk.metadata["flight_frames"] == 0
    np.testing.assert_allclose(np.linalg.norm(walk.rotations_wxyz, axis=-1), 1.0, atol=1e-6)


def test_walk_foot_contact(walk, model, sole_sides):
    v = _pose(model, walk)
    low, speeds = _contact_stats(v, sole_sides, walk.fps_hz)
    lowest = np.minimum(low["L"], low["R"])
    np.testing.assert_allclose(lowest, 0.0, atol=1e-5)  # a foot on the ground in every frame, none below
    assert len(speeds) > 0.5 * walk.num_frames  # mostly single support
    assert np.median(speeds) < 1e-3  # the stance foot does not slide (walking speed 1.3 m/s)
    assert np.quantile(speeds, 0.95) < 0.01 and speeds.max() < 0.1
    # the swing foot clears the ground; both feet down only around the hand-over (double support)
    double = (low["L"] < 1e-3) & (low["R"] < 1e-3)
    assert double.sum() < 0.3 * walk.num_frames
    assert np.maximum(low["L"], low["R"]).max() > 0.02


def test_run_has_flight_and_differs_from_walk(run, walk, model, sole_sides):
    v = _pose(model, run)
    low, speeds = _contact_stats(v, sole_sides, run.fps_hz)
    flight = (low["L"] > 0.005) & (low["R"] > 0.005)
    assert run.metadata["flight_frames"] > 0 and flight.sum() >= 0.1 * run.num_frames
    assert np.minimum(low["L"], low["R"]).min() > -1e-5
    assert np.median(speeds) < 1e-3 and np.quantile(speeds, 0.9) < 0.05
    assert run.speed_m_s == pytest.approx(3.2, rel=1e-3)
    assert run.metadata["cadence_steps_min"] > walk.metadata["cadence_steps_min"] + 30
    assert run.metadata["stance_fraction"] < 0.5 < walk.metadata["stance_fraction"]


def test_heading_turning_and_variation(asset, walk):
    east = generate_gait(GaitParams(speed_m_s=1.3, heading_rad=math.pi / 2), asset, 0)
    np.testing.assert_allclose(east.cycle_advance_m, [-walk.cycle_advance_m[1], 0, 0], atol=1e-9)
    straight = generate_gait(GaitParams(speed_m_s=1.3), asset, 0, fps_hz=60)
    turning = generate_gait(GaitParams(speed_m_s=1.3, turn_rate_rad_s=0.5), asset, 0, fps_hz=60, num_cycles=2)
    assert not turning.is_cycle and turning.num_frames == 2 * straight.num_frames
    path = turning.root_translation_m[:, :2].astype(np.float64)
    start, end = path[1] - path[0], path[-1] - path[-2]
    turned = math.atan2(start[0] * end[1] - start[1] * end[0], start @ end)
    assert turned == pytest.approx(0.5 * turning.duration_s, abs=0.15)
    a = generate_gait(GaitParams(variation=1.0, seed=1), asset, 0, fps_hz=60)
    b = generate_gait(GaitParams(variation=1.0, seed=1), asset, 0, fps_hz=60)
    c = generate_gait(GaitParams(variation=1.0, seed=2), asset, 0, fps_hz=60)
    np.testing.assert_array_equal(a.rotations_wxyz, b.rotations_wxyz)
    assert a.num_frames != c.num_frames or not np.allclose(a.rotations_wxyz, c.rotations_wxyz, atol=1e-3)
    assert a.speed_m_s == pytest.approx(1.3, rel=1e-3)


def test_parameters_are_validated(asset):
    with pytest.raises(ValueError):
        GaitParams(speed_m_s=0)
    with pytest.raises(ValueError):
        GaitParams(run=1.5)
    with pytest.raises(ValueError):
        GaitParams(cadence_steps_min=110, stride_m=1.4)
    with pytest.raises(ValueError):
        generate_gait(GaitParams(), asset, 0, num_cycles=0)
    with pytest.warns(UserWarning, match="cadence changed"):
        slow = generate_gait(GaitParams(speed_m_s=1.3, cadence_steps_min=40), asset, 0, fps_hz=60)
    assert slow.speed_m_s == pytest.approx(1.3, rel=1e-3)


def test_scene_renders_a_generated_gait(asset, model, walk):
    """The renderer's contract: any Motion ([T, J, 4] wxyz + [T, 3] root at fps) drives render_clip."""
    from davis_rig.scene.motion import loop
    from davis_rig.scene.scene import SceneSpec, render_clip

    spec = SceneSpec(motion=loop(walk, 2), duration_s=0.015, heading_rad=math.pi / 2, supersample=1)
    clip = render_clip(spec, model=model)
    assert tuple(clip.video.shape) == (spec.num_frames, 240, 304) and spec.num_frames >= 3
    assert np.isfinite(clip.boxes).all()
    widths = clip.boxes[:, 2] - clip.boxes[:, 0]
    heights = clip.boxes[:, 3] - clip.boxes[:, 1]
    assert (heights > 2 * widths).all() or (heights > 100).all()  # an upright person, not a lying one


def _rendered_contact(vertices, sides, fps):
    """Lowest vertex per frame and the single-support slip (m/s): the foot below the other by > 1 cm carries the
    body; its lowest vertex at frame k must not move in X/Y by frame k + 1."""
    low = {s: vertices[:, ids, 2].min(axis=1) for s, ids in sides.items()}
    speeds = []
    for s, o in (("L", "R"), ("R", "L")):
        ids = sides[s]
        single = low[o] - low[s] > 0.01
        pivot = np.argmin(vertices[:, ids, 2], axis=1)
        k = np.flatnonzero(single[:-1] & single[1:])
        speeds.append(np.linalg.norm(vertices[k + 1, ids[pivot[k]], :2] - vertices[k, ids[pivot[k]], :2], axis=1) * fps)
    return np.minimum(low["L"], low["R"]), np.concatenate(speeds)


def test_the_scenes_default_walk_is_natural_and_on_the_ground_at_every_rendered_frame(asset, model, sole_sides):
    # the bundled cycle moves at 0.53 m/s, 1.2 steps/s, and its 24 Hz keyframes interpolated at 200 fps sink the
    # feet by up to 7.8 mm and slide the planted foot at up to 80 mm/s; the scenes' default walk is the generator's
    from davis_rig.scene.gait import natural_walk
    from davis_rig.scene.scene import SceneSpec, scene_vertices

    walk = natural_walk(asset, 0)
    assert natural_walk(asset, 0) is walk  # generated once per asset and shape
    assert walk.speed_m_s == pytest.approx(1.3, rel=1e-3)
    assert 1.8 < walk.metadata["cadence_steps_min"] / 60 < 2.1  # steps/s (normal walking ~1.9)
    assert SceneSpec().walk == "natural"
    lows = {}
    for name in ("natural", "bundled"):
        for playback, start in ((1.0, 0.3023), (5 / 3, 0.7011)):  # frames between the walk's own frames
            spec = SceneSpec(walk=name, duration_s=1.0, playback_speed=playback, motion_start_s=start,
                             heading_rad=math.pi / 2)
            v = scene_vertices(spec, model).double().numpy()
            lowest, slip = _rendered_contact(v, sole_sides, spec.render_rate_hz)
            lows.setdefault(name, []).append(np.abs(lowest).max())
            if name == "natural":
                x = v[:, :, 0].mean(1)
                assert (x[-1] - x[0]) / (spec.num_frames - 1) * spec.render_rate_hz / playback == pytest.approx(
                    1.3, rel=0.05)  # walking to the image right at its speed
                assert lowest.min() > -1e-4 and lowest.max() < 1e-3  # measured -0.05 .. +0.82 mm
                assert len(slip) > 0.5 * spec.num_frames and np.median(slip) < 1e-3
                assert np.quantile(slip, 0.95) < 5e-3  # measured <= 1.9 mm/s
    assert max(lows["natural"]) < 0.2 * max(lows["bundled"])
    in_place = natural_walk(asset, 0, advance=False)
    assert in_place.speed_m_s == 0.0 and np.array_equal(in_place.rotations_wxyz, walk.rotations_wxyz)
