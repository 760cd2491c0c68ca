"""The chaser keeps clear of the whole target (body, boom, solar array): the truth refuses scenarios that fly
into it, random views never put the camera in or near it nor cut it with the near plane, sequence mode checks
its depth range, and the physics step count is bounded.

The reference geometry here is independent of envisat_pose.datagen.clearance: points sampled on the surface of
every target geom as MuJoCo places it (geom_xpos, geom_xmat, geom_size after mj_forward at the identity pose),
the boom as a true cylinder."""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import mujoco
import numpy as np
import pytest
from scipy.spatial import cKDTree

from envisat_pose.attitude import mrp_to_dcm
from envisat_pose.config import ConfigError, from_dict
from envisat_pose.datagen.clearance import clearance_m, project_target_boxes
from envisat_pose.datagen.generate_config import GenerateConfig
from envisat_pose.datagen.scenario import scenario_config
from envisat_pose.datagen.truth import simulate_truth
from envisat_pose.datagen.views import R_K_FROM_C, sample_random_view
from envisat_pose.geometry import model_path
from envisat_pose.named_scenarios import names as scenario_names

SPACING_M = 0.05  # surface sample spacing: a sampled distance overestimates the true one by < SPACING_M


def _grid(half_u, half_v, step):
    u = np.linspace(-half_u, half_u, max(2, int(np.ceil(2 * half_u / step)) + 1))
    v = np.linspace(-half_v, half_v, max(2, int(np.ceil(2 * half_v / step)) + 1))
    return np.stack(np.meshgrid(u, v, indexing="ij"), -1).reshape(-1, 2)


def box_surface(half, step):
    """Points on the six faces of a box with half sizes `half`, in its own frame. (P, 3)."""
    pts = []
    for axis in range(3):
        a, b = [i for i in range(3) if i != axis]
        uv = _grid(half[a], half[b], step)
        for sign in (-1.0, 1.0):
            p = np.zeros((len(uv), 3))
            p[:, a], p[:, b], p[:, axis] = uv[:, 0], uv[:, 1], sign * half[axis]
            pts.append(p)
    return np.concatenate(pts)


def cylinder_surface(radius, half_length, step):
    """Points on a cylinder along its z axis (mantle and both caps), in its own frame. (P, 3)."""
    n_phi = max(8, int(np.ceil(2 * np.pi * radius / step)))
    phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    z = np.linspace(-half_length, half_length, int(np.ceil(2 * half_length / step)) + 1)
    P, Z = np.meshgrid(phi, z, indexing="ij")
    mantle = np.stack([radius * np.cos(P), radius * np.sin(P), Z], -1).reshape(-1, 3)
    r = np.linspace(0, radius, 3)
    R, P2 = np.meshgrid(r, phi, indexing="ij")
    disc = np.stack([R * np.cos(P2), R * np.sin(P2)], -1).reshape(-1, 2)
    caps = [np.column_stack([disc, np.full(len(disc), s * half_length)]) for s in (-1, 1)]
    return np.concatenate([mantle] + caps)


@pytest.fixture(scope="module")
def surface_T():
    """Points on every geom of body `target`, in T (the body frame), from MuJoCo's own placement. (P, 3) m."""
    m = mujoco.MjModel.from_xml_path(model_path())
    d = mujoco.MjData(m)
    adr = m.joint("target_free").qposadr[0]
    d.qpos[adr : adr + 7] = [0, 0, 0, 1, 0, 0, 0]
    mujoco.mj_forward(m, d)
    body = m.body("target").id
    pts, kinds = [], set()
    for g in range(m.ngeom):
        if m.geom_bodyid[g] != body:
            continue
        kind = m.geom_type[g]
        kinds.add(int(kind))
        if kind == mujoco.mjtGeom.mjGEOM_BOX:
            local = box_surface(m.geom_size[g], SPACING_M)
        elif kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
            local = cylinder_surface(m.geom_size[g][0], m.geom_size[g][1], SPACING_M)
        else:
            raise AssertionError(f"geom type {kind} not covered by this test")
        pts.append(d.geom_xpos[g] + local @ d.geom_xmat[g].reshape(3, 3).T)
    assert {int(mujoco.mjtGeom.mjGEOM_BOX), int(mujoco.mjtGeom.mjGEOM_CYLINDER)} <= kinds
    return np.concatenate(pts)


def test_clearance_against_the_sampled_surface(surface_T):
    """Box clearance (MuJoCo's bounding boxes) never exceeds the distance to the true surface, and is within
    the boom's bounding-box slack of it; the array's outer corner sets the reach (reference sheet: ~22.1 m)."""
    tree = cKDTree(surface_T)
    rng = np.random.default_rng(0)
    pts = rng.uniform([-26, -6, -6], [9, 6, 6], size=(4000, 3))
    d_box, _ = clearance_m(pts, project_target_boxes())
    d_ref, _ = tree.query(pts)
    outside = d_box > 0
    assert outside.sum() > 3000
    assert np.all(d_box[outside] <= d_ref[outside] + 1e-9)  # conservative: never farther than the surface
    assert np.all(d_ref[outside] - d_box[outside] < 0.08 * (np.sqrt(2) - 1) + SPACING_M)  # boom corner slack
    # the main body is solid (its faces are thin plates in the MJCF); the array plate is 4 cm thick
    d_in, part = clearance_m(np.array([[0.0, 0.0, 0.0], [4.0, 1.0, 0.9], [-15.0, 1.0, 0.0]]), project_target_boxes())
    np.testing.assert_allclose(d_in, [-1.0375, -0.1375, -0.02], atol=1e-12)
    assert [project_target_boxes().names[i] for i in part] == ["body", "body", "array"]
    assert abs(project_target_boxes().reach_m - np.linalg.norm(surface_T, axis=1).max()) < 1e-9
    assert abs(project_target_boxes().reach_m - np.linalg.norm([22.0, 2.5, 0.02])) < 1e-9


def test_a_15m_hold_through_the_array_is_refused(surface_T, monkeypatch):
    """The old close_15m (rho0 = 15 m along V-bar): seed 0 flies the chaser through the array plate."""
    import envisat_pose.datagen.truth as truth

    cfg = scenario_config(seed=0, relative={"rho0_C_m": [0.0, 15.0, 0.0]})
    with pytest.raises(ConfigError) as err:
        simulate_truth(cfg)
    text = str(err.value)
    assert err.value.field == "relative.rho0_C_m" and err.value.value == [0.0, 15.0, 0.0]
    assert "keepout_margin_m = 2 m" in text and "from geom 'array'" in text
    t_s = float(text.split("at t = ")[1].split(" s")[0])
    dist_m = float(text.split("the chaser is ")[1].split(" m")[0])
    # independent: the same truth without the check; the chaser in T against the sampled surface
    monkeypatch.setattr(truth, "check_clearance", lambda *args: None)
    tr = simulate_truth(cfg)
    k = int(np.flatnonzero(tr.t_s == t_s)[0])
    c_T = -mrp_to_dcm(tr.x[:, 6:9]) @ tr.x[:, 0:3, None]
    d_ref = cKDTree(surface_T).query(c_T[:, :, 0])[0]
    assert abs(d_ref[k] - dist_m) < SPACING_M + 0.01
    assert d_ref[:k].min() >= 2.0 - SPACING_M and d_ref[k] < 2.0  # the first time it comes within 2 m
    assert d_ref.min() < 0.2  # and later it grazes or crosses the plate (4 cm thick)


def test_close_25m_keeps_clear_for_many_seeds(surface_T):
    assert "close-15m" not in scenario_names() and "close-25m" in scenario_names()
    reach_m = np.linalg.norm(surface_T, axis=1).max()
    tree = cKDTree(surface_T)
    for seed in range(6):
        tr = simulate_truth(scenario_config("close-25m", seed=seed))
        assert abs(tr.x[0, 1] - 25.0) < 1e-12
        # attitude-free: the chaser stays beyond the array's reach plus the margin
        assert np.linalg.norm(tr.x[:, 0:3], axis=1).min() - reach_m > 2.0
        c_T = -np.einsum("nij,nj->ni", mrp_to_dcm(tr.x[::10, 6:9]), tr.x[::10, 0:3])
        assert tree.query(c_T)[0].min() > 2.0


@pytest.mark.parametrize("overrides, message", [
    ({"max_physics_dt_s": 1e-9}, "max_physics_dt_s = 1e-09"),
    ({"max_physics_dt_s": 1e-4, "duration_s": 1.0e5}, "RK4 steps"),
    ({"keepout_margin_m": -1.0}, "keepout_margin_m = -1.0"),
])
def test_physics_step_and_margin_are_bounded(overrides, message):
    """A physics step of 1e-9 s would take ~1e12 RK4 steps for the default 30 minutes: refused up front."""
    with pytest.raises(ConfigError, match=message):
        scenario_config(**overrides)


def znear_of_renderer():
    from envisat_pose.datagen.render import SceneRenderer

    r = SceneRenderer(64)
    try:
        return r.znear_m, r.fovy_deg
    finally:
        r.close()


def test_random_views_keep_the_camera_clear_and_the_target_beyond_the_near_plane(surface_T):
    """Down to 12 m (allowed: range_min_m > reach / 2) the array can reach the camera; every drawn view must
    still keep keepout_margin_m from the sampled surface and put all of it in front of the near plane."""
    znear_m, fovy_deg = znear_of_renderer()
    cfg = from_dict(GenerateConfig, {"random": {"range_min_m": 12.0, "range_max_m": 30.0, "max_offset_frac": 1.0}})
    tree = cKDTree(surface_T)
    min_clear, min_z = np.inf, np.inf
    for seed in range(1500):
        view, x, _ = sample_random_view(cfg, fovy_deg, np.random.default_rng(seed))
        R_C_T = np.asarray(view.R_C_from_T)
        c_T = -R_C_T.T @ view.rho_C_m
        min_clear = min(min_clear, tree.query(c_T)[0])
        z_K = (view.rho_C_m + surface_T @ R_C_T.T) @ R_K_FROM_C[2]
        min_z = min(min_z, z_K.min())
        assert 12.0 - 1e-9 <= np.linalg.norm(view.rho_C_m) <= 30.0 + 1e-9
    assert min_clear >= 2.0  # keepout_margin_m, default
    assert min_z > znear_m
    # and the same seed gives the same view (the redraws come from the sample's own generator)
    a = sample_random_view(cfg, fovy_deg, np.random.default_rng(77))[1]
    b = sample_random_view(cfg, fovy_deg, np.random.default_rng(77))[1]
    np.testing.assert_array_equal(a, b)


def test_sequence_mode_refuses_a_depth_range_that_misses_the_target(tmp_path, capsys):
    """At 50 m the target's far side is ~59 m deep; 65535 x 0.0005 m = 32.8 m cannot encode it."""
    from envisat_pose.app.cli import main

    cfg_path = tmp_path / "seq.toml"
    cfg_path.write_text('mode = "sequence"\ndepth_scale_m = 0.0005\n')
    out = tmp_path / "ds"
    rc = main(["generate", "--config", str(cfg_path), "--num-images", "3", "--resolution", "64", "--out", str(out),
               "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert "depth_scale_m = 0.0005" in err and "32.8 m" in err
    assert not out.exists()
