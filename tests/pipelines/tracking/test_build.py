"""The public API a library user calls (issue 27): the builders exported from `envisat_pose`, a FilterConfig
that overrides only the fields it gives, and est.npz's status rows (NaN where the tracker holds no estimate)
under the Estimates contract."""

import dataclasses

import numpy as np
import pytest


def test_the_builders_are_public_and_build_what_they_say():
    import envisat_pose
    from envisat_pose.datagen.orbit import chaser_orbit
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.geometry import load_camera

    for name in ("tracker_camera", "tracker_detector", "chaser_from_orbit", "tracker_filter", "tracker_from_scenario"):
        assert name in envisat_pose.__all__ and callable(getattr(envisat_pose, name))
    cam = envisat_pose.tracker_camera(size_px=(512, 256))
    mjcf = load_camera()
    # the same vertical field of view (MuJoCo's fovy) read out at another size: f scales with the height
    assert (cam.width_px, cam.height_px) == (512, 256) and cam.f_px == pytest.approx(mjcf.f_px * 256 / mjcf.height_px)
    chaser_at = envisat_pose.chaser_from_orbit()
    orb = chaser_orbit(scenario_config("default").orbit, np.array([123.0]))
    np.testing.assert_allclose(chaser_at(123.0), [orb.r_m[0], orb.rdot_m_s[0], orb.theta_rad[0],
                                                  orb.thetadot_rad_s[0]])
    # an orbit given as a dict of its fields: a higher orbit is slower
    slow = envisat_pose.chaser_from_orbit({"a_m": 8000e3, "e": 0.0})
    assert slow(0.0)[0] == pytest.approx(8000e3) and slow(0.0)[3] < chaser_at(0.0)[3]


def test_a_filter_config_overrides_only_the_fields_it_gives():
    """The tracker's filter defaults (adaptive R, no gate lockout) stay when a user passes FilterConfig(alpha=...):
    the old Tracker replaced them all by FilterConfig's own defaults."""
    from envisat_pose.filtering.estimator import FilterConfig
    from envisat_pose.pipelines.tracking.build import tracker_filter
    from envisat_pose.pipelines.tracking.tracker import TRACKER_FILTER

    default = FilterConfig()
    field = next(f.name for f in dataclasses.fields(FilterConfig)
                 if f.name not in TRACKER_FILTER and isinstance(getattr(default, f.name), float))
    new = getattr(default, field) * 0.5
    merged = tracker_filter(FilterConfig(**{field: new}))
    assert getattr(merged, field) == new
    for key, value in TRACKER_FILTER.items():
        assert getattr(merged, key) == value, key
    # a dict sets exactly its keys, a FilterConfig default included
    assert tracker_filter({"adaptive_r": False}).adaptive_r is False
    assert tracker_filter(None).adaptive_r is True
    # the Tracker itself merges the same way
    from envisat_pose.pipelines.tracking.tracker import Tracker

    tracker = Tracker.from_scenario("default", filter_config=FilterConfig(**{field: new}), size_px=(128, 128))
    assert getattr(tracker.fcfg, field) == new and tracker.fcfg.adaptive_r is True
    assert tracker.camera.width_px == 128


def test_estimates_rows_without_an_estimate_are_nan_and_say_so(tmp_path):
    from envisat_pose.contracts import ContractError, Estimates

    T = 4
    x = np.zeros((1, T, 12))
    x[..., 1] = 50.0
    P = np.broadcast_to(np.eye(12), (1, T, 12, 12)).copy()
    status = np.array([[0, 0, 1, 3]])
    x_hat, P_hat = x.copy(), P.copy()
    x_hat[0, :2], P_hat[0, :2] = np.nan, np.nan
    est = Estimates(t_s=np.arange(T, dtype=float), x_true=x, x_hat=x_hat, P=P_hat, n_meas=np.zeros((1, T), int),
                    nis=np.zeros((1, T)), nis_dof=np.zeros((1, T), int), diverged=np.zeros(1, bool),
                    config_json="{}", status=status)
    est.save(str(tmp_path / "est.npz"))
    back = Estimates.load(str(tmp_path / "est.npz"))
    np.testing.assert_array_equal(back.status, status)
    with np.load(tmp_path / "est.npz") as z:
        assert "acquiring" in str(z["status_legend"])
    # NaN on a tracking row, or NaN without a status, is not an estimate file
    bad = x_hat.copy()
    bad[0, 2, 0] = np.nan
    with pytest.raises(ContractError, match="x_hat"):
        dataclasses.replace(est, x_hat=bad).save(str(tmp_path / "bad.npz"))
    with pytest.raises(ContractError, match="x_hat"):
        dataclasses.replace(est, status=None).save(str(tmp_path / "bad.npz"))
    with pytest.raises(ContractError, match="status"):
        dataclasses.replace(est, status=np.array([[0, 0, 1, 7]])).save(str(tmp_path / "bad.npz"))


def test_a_camera_file_of_frames_that_need_undistorting_is_refused_not_stripped(tmp_path):
    """tracker_camera(path) gives the pinhole of an ideal camera file; a file with distortion or non-square pixels
    is one line naming the key (the Tracker takes ideal frames, and the bare pinhole would drop the remap that
    camera_from_intrinsics returns with it)."""
    from envisat_pose.config import InputError
    from envisat_pose.pipelines.tracking.build import tracker_camera
    from envisat_pose.pipelines.tracking.camera_file import camera_from_intrinsics

    base = "fx = 300.0\ncx = 63.5\ncy = 63.5\nwidth = 128\nheight = 128\n"
    ideal = tmp_path / "ideal.toml"
    ideal.write_text(base + "fy = 300.0\ndistortion = [0.0, 0.0, 0.0, 0.0]\n")
    cam = tracker_camera(str(ideal))
    assert (cam.f_px, cam.cu_px, cam.width_px, cam.height_px) == (300.0, 63.5, 128, 128)
    for name, extra, key in (("distorted", "fy = 300.0\ndistortion = [-0.2, 0.05, 0.0, 0.0]\n", "distortion = "),
                             ("oblong", "fy = 330.0\n", "fx = 300.0, fy = 330.0")):
        path = tmp_path / f"{name}.toml"
        path.write_text(base + extra)
        assert camera_from_intrinsics(str(path))[1] is not None  # these frames need the remap
        with pytest.raises(InputError, match=f"{name}.toml: {key}.*need undistorting") as err:
            tracker_camera(str(path))
        assert "\n" not in str(err.value)
