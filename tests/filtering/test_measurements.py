"""Measurement models against MuJoCo (the corner sites and the chaser camera of models/envisat.xml)."""

import numpy as np
import pytest

from envisat_pose.filtering.measurements import (
    corners_C_m,
    corners_in_frame,
    limit_markers,
    measure,
    outage_mask,
    predicted_visible,
    random_failures,
    swap_corners,
)
from envisat_pose.geometry import load_camera


@pytest.fixture(scope="module")
def mujoco_state():
    """A MuJoCo truth state after 137 RK4 steps: the 12-state and the corner sites in C."""
    from envisat_pose.datagen.orbit import chaser_orbit
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.sim import TruthSim
    from envisat_pose.datagen.truth import initial_state

    # 15 m: the body overflows the field of view (in_frame is tested below); a few RK4 steps, no trajectory
    cfg = scenario_config("default", relative={"rho0_C_m": [0.0, 15.0, 0.0]})
    sim = TruthSim(cfg)
    sim.set_state(initial_state(cfg, np.random.default_rng(3)), 0.0)
    sim.step(137)
    sim.sync_chaser()
    R_N_C = chaser_orbit(cfg.orbit, np.array([sim.data.time])).R_N_from_C[0]
    sites_C = (sim.data.site_xpos[sim.corner_site_ids] - sim.data.mocap_pos[0]) @ R_N_C
    return sim, sim.relative_state(), sites_C


def test_3d_corners_equal_mujoco_sites(mujoco_state):
    _, x, sites_C = mujoco_state
    np.testing.assert_allclose(measure(x, "markers3d"), sites_C, atol=1e-9)
    # Gamma (not its transpose) would put the corners meters away
    from envisat_pose.attitude import mrp_to_dcm
    from envisat_pose.geometry import load_geometry
    wrong = x[:3] + load_geometry().corners_T_m @ mrp_to_dcm(x[6:9]).T
    assert np.abs(wrong - sites_C).max() > 0.5


def test_filter_pixels_are_mujocos_projection_of_the_truth(truth_600):
    """The filter's pixel model (the MJCF camera through load_camera) against the truth's corners_px, which MuJoCo
    projects through its compiled camera: the same camera, to numerical precision (a copied focal length of
    1910.8 px instead of the MJCF's 1910.85 would be off by ~5e-3 px at the image edges)."""
    tr = truth_600
    uv = measure(tr.x, "pixels")
    seen = tr.in_frame
    assert seen.mean() > 0.9
    np.testing.assert_allclose(uv[seen], tr.corners_px[seen], rtol=0, atol=1e-5)
    uvr = measure(tr.x, "pixels+range")
    np.testing.assert_allclose(uvr[..., 2], np.linalg.norm(tr.corners_C_m - load_camera().pos_C_m, axis=-1), atol=1e-8)
    np.testing.assert_array_equal(corners_in_frame(tr.x), tr.in_frame)


def test_a_corner_behind_the_camera_is_never_mirrored_into_the_image():
    """Target 50 m behind the chaser (-y_C): a plain pinhole would mirror every corner into the image (z_K < 0 flips
    the signs); the guarded projection puts them far outside, on their own side of the principal point."""
    cam = load_camera()
    x = np.zeros(12)
    x[:3] = [3.0, -50.0, 2.0]
    x[6:9] = [0.1, -0.2, 0.3]
    pts_K = (corners_C_m(x) - cam.pos_C_m) @ cam.R_K_from_C.T
    assert (pts_K[:, 2] < 0).all()
    mirrored = cam.f_px * pts_K[:, :2] / pts_K[:, 2:3] + [cam.cu_px, cam.cv_px]
    assert ((mirrored >= 0) & (mirrored <= 1023)).all()  # what an unguarded pinhole would report
    for kind in ("pixels", "pixels+range"):
        uv = measure(x, kind)[:, :2]
        assert (np.abs(uv - [cam.cu_px, cam.cv_px]) > 1e4).any(axis=1).all()
        np.testing.assert_array_equal(np.sign(uv - [cam.cu_px, cam.cv_px]), np.sign(pts_K[:, :2]))
    assert not corners_in_frame(x).any()


def test_pixels_and_range(mujoco_state):
    _, x, sites_C = mujoco_state
    cam = load_camera()
    uv = measure(x, "pixels", cam)
    for i in range(8):
        v_K = cam.R_K_from_C @ (sites_C[i] - cam.pos_C_m)
        np.testing.assert_allclose(uv[i], [cam.f_px * v_K[0] / v_K[2] + 511.5, cam.f_px * v_K[1] / v_K[2] + 511.5],
                                   atol=1e-6)
    uvr = measure(x, "pixels+range", cam)
    np.testing.assert_allclose(uvr[:, :2], uv)
    np.testing.assert_allclose(uvr[:, 2], np.linalg.norm(sites_C - cam.pos_C_m, axis=1), atol=1e-9)
    # the target ahead (+y_C) is in the middle of the image; something radially above (+x_C) is up (small v)
    up = np.array([0.0, 0.0, 0.0] + [0.0] * 9)
    up[:3] = [5.0, 50.0, 0.0]
    assert measure(up, "pixels", cam)[:, 1].mean() < 511.5
    # at 15 m the 10 m body overflows the 30 deg field of view; at 50 m every corner is in the image
    assert not corners_in_frame(x, cam).all()
    x50 = x.copy()
    x50[:3] = [0.0, 50.0, 0.0]
    assert corners_in_frame(x50, cam).all()


def test_predicted_visibility_is_the_exact_face_test(mujoco_state):
    _, x, sites_C = mujoco_state
    vis = predicted_visible(x)
    assert vis.sum() in (4, 6, 7)
    # independent check: a box corner is visible iff the segment from the camera to it does not cross the box
    from envisat_pose.attitude import mrp_to_dcm
    from envisat_pose.geometry import load_geometry

    g = load_geometry()
    G = mrp_to_dcm(x[6:9])
    c_T = -G @ x[:3]
    half = g.half_sizes_m
    for i, v in enumerate(g.corners_T_m):
        s = np.linspace(0.0, 0.999, 4000)[:, None]
        pts = c_T + s * (v - c_T)
        inside = (np.abs(pts) < half - 1e-6).all(axis=1)
        assert vis[i] == (not inside.any())


def test_selection_rules():
    rng = np.random.default_rng(0)
    mask = rng.random((1000, 8)) < 0.8
    lim = limit_markers(mask, 3)
    assert (lim.sum(-1) == np.minimum(mask.sum(-1), 3)).all()
    assert not (lim & ~mask).any()
    first = np.argmax(mask, axis=-1)
    assert lim[np.arange(1000), first].all()  # the first visible corner (A..H order) is always kept
    fail = random_failures(np.ones((20000, 8), bool), 0.2, np.random.default_rng(1))
    assert abs(1 - fail.mean() - 0.2) < 0.01
    t = np.arange(100.0)
    out = outage_mask(t, ((10.0, 20.0), (50.0, 51.0)))
    assert out.sum() == 11 and out[10] and not out[20] and out[50]
    z = np.arange(3 * 8 * 3, dtype=float).reshape(3, 8, 3)
    sw = swap_corners(z, np.array([False, True, False]), 0, 2)
    np.testing.assert_array_equal(sw[1, 0], z[1, 2])
    np.testing.assert_array_equal(sw[1, 2], z[1, 0])
    np.testing.assert_array_equal(sw[0], z[0])


def test_batched_states_each_get_their_own_measurements():
    """(4, 25, 12) states, all different (range 40-60 m, any attitude): every batched output has the leading
    shape and equals, element by element, an independent computation for that one state: the corners
    rho + R v with R from scipy's MRP rotation (active, Gamma^T), the pinhole u = f x_K / z_K + c in the camera
    frame, the range from the camera, and a corner visible iff the chaser is outside the box's slab of one of its
    three faces (s_j c_T[j] > h_j, c_T = -Gamma rho); and in_frame equals the pixel bounds."""
    from scipy.spatial.transform import Rotation

    from envisat_pose.geometry import load_geometry

    rng = np.random.default_rng(7)
    B = (4, 25)
    x = np.zeros(B + (12,))
    x[..., 0:3] = rng.normal(0.0, 4.0, B + (3,)) + [0.0, 50.0, 0.0]
    x[..., 3:6] = rng.normal(0.0, 0.01, B + (3,))
    x[..., 6:9] = rng.uniform(-0.6, 0.6, B + (3,))
    x[..., 9:12] = rng.normal(0.0, 0.03, B + (3,))
    cam, g = load_camera(), load_geometry()
    got = {"corners": corners_C_m(x), "pixels": measure(x, "pixels", cam), "pr": measure(x, "pixels+range", cam),
           "visible": predicted_visible(x), "in_frame": corners_in_frame(x, cam)}
    assert got["corners"].shape == B + (8, 3) and got["pixels"].shape == B + (8, 2)
    assert got["pr"].shape == B + (8, 3) and got["visible"].shape == got["in_frame"].shape == B + (8,)
    signs = np.sign(g.corners_T_m)
    for idx in np.ndindex(*B):
        xi = x[idx]
        R = Rotation.from_mrp(xi[6:9]).as_matrix()  # active: Gamma^T
        c = xi[0:3] + g.corners_T_m @ R.T
        np.testing.assert_allclose(got["corners"][idx], c, rtol=0, atol=1e-12)
        p_K = (c - cam.pos_C_m) @ cam.R_K_from_C.T
        uv = cam.f_px * p_K[:, :2] / p_K[:, 2:3] + [cam.cu_px, cam.cv_px]
        np.testing.assert_allclose(got["pixels"][idx], uv, rtol=0, atol=1e-8)
        np.testing.assert_allclose(got["pr"][idx][:, :2], uv, rtol=0, atol=1e-8)
        np.testing.assert_allclose(got["pr"][idx][:, 2], np.linalg.norm(c - cam.pos_C_m, axis=1), rtol=0, atol=1e-9)
        c_T = -R.T @ xi[0:3]
        np.testing.assert_array_equal(got["visible"][idx], (signs * c_T > g.half_sizes_m).any(axis=1))
        inside = (uv >= -0.5).all(axis=1) & (uv[:, 0] <= cam.width_px - 0.5) & (uv[:, 1] <= cam.height_px - 0.5)
        np.testing.assert_array_equal(got["in_frame"][idx], inside & (p_K[:, 2] > 0))
    # the states differ, and so do their measurements (a batch that broadcast one state would pass the shapes)
    assert np.ptp(got["pixels"], axis=(0, 1)).min() > 10.0
    assert got["visible"].reshape(-1, 8).any(axis=0).all() and not got["visible"].all()


def test_detections_become_filter_input():
    from envisat_pose.filtering.measurements import from_detections

    rng = np.random.default_rng(2)
    corners = rng.uniform(0, 1023, (5, 8, 2))
    corners[1, 3] = np.nan
    cov = np.broadcast_to(np.diag([2.0, 0.5]), (5, 8, 2, 2)).copy()
    cov[2, 4, 0, 0] = np.inf
    visible = np.ones((5, 8), bool)
    visible[0, 0] = False
    conf = np.full((5, 8), 0.9)
    conf[3, 7] = 0.1
    z, mask, R_c = from_detections(corners, cov, visible, conf, min_confidence=0.5)
    assert mask.sum() == 40 - 4
    assert not mask[0, 0] and not mask[1, 3] and not mask[2, 4] and not mask[3, 7]
    assert np.isfinite(z).all() and np.isfinite(R_c).all()
    np.testing.assert_array_equal(R_c[4], cov[4])
