"""The benchmarks' random trials (pipelines/runs/trials.py): a drawn sun lights every frame (checked with an LVLH frame
and an Earth shadow built here from the chaser's inertial position and velocity), draws are reproducible from the
seed, and an acquisition trial's truth holds the drawn range, axis and attitude."""

import numpy as np
import pytest

from envisat_pose.datagen.orbit import chaser_orbit
from envisat_pose.datagen.scenario import scenario_config
from envisat_pose.pipelines.runs.trials import (
    draw_lit_sun_N,
    random_attitude_mrp,
    scenario_sun_N,
    sun_rng,
    trial_truth_config,
    unit_vector,
)

EARTH_RADIUS_M = 6378137.0  # WGS-84 equatorial radius


def lvlh_axes_N(r_N: np.ndarray, v_N: np.ndarray) -> np.ndarray:
    """(T, 3, 3) columns: radial, along-track (completing), orbit normal, in N."""
    x = r_N / np.linalg.norm(r_N, axis=-1, keepdims=True)
    z = np.cross(r_N, v_N)
    z /= np.linalg.norm(z, axis=-1, keepdims=True)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def test_a_drawn_sun_lights_every_frame_of_the_run():
    scen = scenario_config("default")
    t_s = np.arange(601.0)
    orb = chaser_orbit(scen.orbit, t_s)
    R = lvlh_axes_N(orb.r_N_m, orb.v_N_m_s)
    to_camera_C = -np.asarray(scen.relative.rho0_C_m) / np.linalg.norm(scen.relative.rho0_C_m)
    for seed in range(5):
        sun = np.array(draw_lit_sun_N(scen.orbit, t_s, scen.relative.rho0_C_m, sun_rng(seed), 60.0))
        assert np.linalg.norm(sun) == pytest.approx(1.0)
        sun_C = np.einsum("tji,j->ti", R, sun)
        assert np.degrees(np.arccos(sun_C @ to_camera_C)).max() <= 60.0 + 1e-6
        along = orb.r_N_m @ sun
        perp = np.linalg.norm(orb.r_N_m - along[:, None] * sun, axis=1)
        assert not ((along < 0) & (perp < EARTH_RADIUS_M)).any()


def test_draws_follow_the_seed():
    a = scenario_sun_N("default", 300.0, 1.0, 3)
    assert a == scenario_sun_N("default", 300.0, 1.0, 3)
    assert a != scenario_sun_N("default", 300.0, 1.0, 4)
    assert scenario_sun_N("eclipse", 300.0, 1.0, 3) is None  # its sun is the scenario's
    r1, r2 = np.random.default_rng(7), np.random.default_rng(7)
    np.testing.assert_array_equal(unit_vector(r1), unit_vector(r2))
    np.testing.assert_array_equal(random_attitude_mrp(r1), random_attitude_mrp(r2))


def test_random_attitudes_cover_the_rotations():
    """Uniform on SO(3): the rotation angle's density is (1 - cos a) / pi, so its mean is pi / 2 + 2 / pi."""
    rng = np.random.default_rng(0)
    p = np.array([random_attitude_mrp(rng) for _ in range(4000)])
    assert (np.linalg.norm(p, axis=1) <= 1.0 + 1e-12).all()
    angle = 4.0 * np.arctan(np.linalg.norm(p, axis=1))
    assert angle.mean() == pytest.approx(np.pi / 2 + 2 / np.pi, abs=0.03)


def test_an_acquisition_trial_holds_its_range_axis_and_attitude():
    cfg = trial_truth_config("stress-tumble", 90.0, 1.0, 5, 30.0, (0.0, 1.0, 0.0), (0.1, 0.2, 0.3))
    assert cfg.relative.rho0_C_m == (0.0, 30.0, 0.0) and cfg.target.spin_period_s == 72.0
    np.testing.assert_allclose(cfg.target.w0_T_rad_s, [0.0, 2 * np.pi / 72.0, 0.0])
    assert cfg.target.p0_mrp == (0.1, 0.2, 0.3) and cfg.duration_s == 90.0 and cfg.dt_s == 1.0 and cfg.seed == 5
