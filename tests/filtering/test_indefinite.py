"""An innovation covariance that is not positive definite is a reported failure, never a negative NIS."""

import numpy as np
import pytest

from envisat_pose.filtering.estimator import FilterConfig, Measurement, filter_step, init_state, make_setup
from envisat_pose.filtering.ukf import positive_definite
from envisat_pose.geometry import load_camera
from envisat_pose.state import N_STATE


def test_positive_definite_tells_indefinite_and_singular_apart():
    good = np.diag([1.0, 2.0])
    indefinite = np.array([[1.0, 2.0], [2.0, 1.0]])  # eigenvalues 3 and -1
    singular = np.array([[1.0, 1.0], [1.0, 1.0]])
    nonfinite = np.array([[np.nan, 0.0], [0.0, 1.0]])
    assert positive_definite(np.stack([good, indefinite, singular, nonfinite])).tolist() == [True, False, False, False]


@pytest.mark.parametrize("kernel", ["fast", "reference"])
def test_indefinite_innovation_covariance_fails_the_update(kernel):
    cam = load_camera()
    cfg = FilterConfig(kernel=kernel)
    setup = make_setup(cfg, "pixels", cam)
    x0 = np.zeros(N_STATE)
    x0[:3] = [0.0, 50.0, 0.0]  # 50 m along +y of C, the default camera's boresight
    x0[6:9] = [0.1, 0.2, 0.05]
    x0[9:] = [0.0, 0.02, 0.0]
    P0 = np.diag([0.05] * 3 + [0.001] * 3 + [1e-4] * 3 + [1e-6] * 3)
    state = init_state(np.stack([x0, x0]), P0, 0.0, np.array([7.0e6, 0.0, 0.0, 1.1e-3]), cfg)
    uv = setup.hx(x0[None])[0]  # (8, 2) the predicted corners: measure exactly them
    z = np.stack([uv, uv])
    mask = np.isfinite(uv).all(-1)[None].repeat(2, 0)
    R_c = np.broadcast_to(np.eye(2), (2, 8, 2, 2)).copy()
    R_c[1] = np.array([[1.0, 0.0], [0.0, -1e9]])  # run 1: a measurement covariance no update can use
    new = filter_step(state, Measurement(1.0, np.array([7.0e6, 0.0, 0.0, 1.1e-3]), np.nan_to_num(z), mask, R_c), setup)
    assert np.all(new.nis >= 0.0)
    assert not new.indefinite[0] and new.n_meas[0] > 0 and not new.diverged[0]
    # the failed run: flagged, nothing used, rolled back to its (finite) prediction
    assert new.indefinite[1] and new.diverged[1] and new.repaired[1] == 1
    assert new.n_meas[1] == 0 and new.dof[1] == 0 and new.nis[1] == 0.0
    assert np.isfinite(new.mean[1]).all() and np.isfinite(new.cov[1]).all()
