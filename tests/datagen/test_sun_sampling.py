"""Random-mode sun directions: uniform on the cap of phase angles the config allows, with a backlit share."""

import math

import numpy as np
import pytest

from envisat_pose.config import ConfigError, from_dict
from envisat_pose.datagen.generate_config import GenerateConfig
from envisat_pose.datagen.views import sample_cap, sample_random_view


def test_cap_samples_are_uniform_on_the_cap():
    rng = np.random.default_rng(0)
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    v = np.array([sample_cap(axis, 60.0, rng) for _ in range(20000)])
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-12)
    cos_t = v @ axis
    assert cos_t.min() >= math.cos(math.radians(60.0)) - 1e-12
    # uniform on a cap: cos(theta) is uniform on [cos 60, 1] (Archimedes), mean 0.75, variance (0.5)^2 / 12
    assert abs(cos_t.mean() - 0.75) < 0.005
    assert abs(cos_t.var() - 0.25 / 12) < 0.001
    # and the azimuth about the axis is uniform: the perpendicular parts average to zero
    perp = v - cos_t[:, None] * axis
    assert np.linalg.norm(perp.mean(axis=0)) < 0.02  # ~4 standard errors; a one-sided azimuth gives ~0.5


def test_default_views_are_mostly_front_lit_with_a_backlit_share():
    cfg = from_dict(GenerateConfig, {})
    rng = np.random.default_rng(5)
    phase = []
    for _ in range(600):
        view, x, scene = sample_random_view(cfg, 30.0, rng)
        if view.sun_dir_C is None:
            continue
        to_camera = -np.asarray(view.rho_C_m) / np.linalg.norm(view.rho_C_m)
        phase.append(math.degrees(math.acos(np.clip(np.asarray(view.sun_dir_C) @ to_camera, -1, 1))))
    phase = np.array(phase)
    beyond = np.mean(phase > cfg.random.sun_phase_max_deg)
    # only backlit draws (15 %, the sphere's share beyond 100 deg: (1 + cos 100)/2 = 41 %) pass the cap: ~6 %
    expected = cfg.random.backlit_probability * (1 + math.cos(math.radians(cfg.random.sun_phase_max_deg))) / 2
    assert abs(beyond - expected) < 0.03
    assert np.mean(phase < 90.0) > 0.75


def test_sun_phase_is_validated():
    with pytest.raises(ConfigError, match="random.sun_phase_max_deg"):
        from_dict(GenerateConfig, {"random": {"sun_phase_max_deg": 200.0}})
    with pytest.raises(ConfigError, match="random.backlit_probability"):
        from_dict(GenerateConfig, {"random": {"backlit_probability": -0.1}})
