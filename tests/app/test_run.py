"""`envisat run`, the online closed loop: the per-frame step against a stub detector (robustness only: nothing,
a wrong corner, garbage, a half-turn, eclipse), the whole loop with the real renderer, detector and filter
(outputs, the recording read back with Rerun's reader, eclipse), and convergence on the default scenario."""

import json
import os
import tomllib

import numpy as np
import pytest

from envisat_pose.app import run as loop
from envisat_pose.filtering.estimator import FilterConfig, chaser_states, init_state, make_setup
from envisat_pose.perception.detect import FrameDetection

IMAGE = np.zeros((8, 8), dtype=np.uint8)  # the stub detector never looks at it


class StubDetector:
    """Returns the FrameDetections it is given, one per call, and records the calls (robustness tests only)."""

    def __init__(self, *frames):
        self.frames, self.calls = list(frames), []

    def detect(self, image, K, roi_px=None, prior_R_cam_from_target=None):
        self.calls.append({"roi_px": roi_px, "prior": prior_R_cam_from_target})
        return self.frames.pop(0) if len(self.frames) > 1 else self.frames[0]


def detection(corners_px, visible, sigma_px=1.0, alt=None, ambiguous=False):
    vis = np.asarray(visible, bool)
    c = np.where(vis[:, None], corners_px, np.nan)
    cov = np.where(vis[:, None, None], np.eye(2) * sigma_px**2, np.nan)
    alt = np.full((8, 2), np.nan) if alt is None else alt
    return FrameDetection(c, cov, vis * 0.9, vis, alt, 0.4 if ambiguous else 0.0, ambiguous, np.array([0.0, 0.0, 1024.0]),
                          c[vis])


def truth_detection(tr, k, noise_px=0.0, rng=None, **kw):
    vis = tr.visible[k] & tr.in_frame[k]
    c = tr.corners_px[k] + (0.0 if rng is None else rng.normal(0.0, noise_px, (8, 2)))
    return detection(c, vis, **kw)


@pytest.fixture(scope="module")
def setup_and_chaser(truth_600):
    tr = truth_600
    cfg = FilterConfig(**{**loop.LOOP_FILTER, "q_sigma": (1e-8, 1e-8, 1e-9, 1e-10)})
    return make_setup(cfg, "pixels"), chaser_states(tr.chaser_r_m, tr.chaser_rdot_m_s, tr.chaser_theta_rad,
                                                    tr.chaser_thetadot_rad_s)


def start(tr, setup, chaser, seed=0, P0=None):
    P0 = setup.cfg.P0 if P0 is None else P0
    rng = np.random.default_rng(seed)
    x0 = tr.x[0] + np.linalg.cholesky(P0) @ rng.standard_normal(12)
    return init_state(x0[None], P0, tr.t_s[0], chaser[0], setup.cfg)


def step(state, tr, k, chaser, det, setup, image=IMAGE, lcfg=loop.LoopConfig()):
    return loop.loop_step(state, loop.FrameInput(float(tr.t_s[k]), chaser[k], image), det, setup, lcfg)


def finite(state):
    return np.isfinite(state.mean).all() and np.isfinite(state.cov).all()


def converged_state(tr, setup, chaser, frames=40):
    rng = np.random.default_rng(7)
    state = start(tr, setup, chaser)
    for k in range(1, frames):
        state, rec = step(state, tr, k, chaser, StubDetector(truth_detection(tr, k, 1.0, rng)), setup)
    return state


def test_nothing_found_a_wrong_corner_and_garbage_leave_the_filter_running(truth_600, setup_and_chaser):
    tr = truth_600
    setup, chaser = setup_and_chaser
    state = converged_state(tr, setup, chaser)
    k = 40
    assert np.linalg.norm(state.mean[0, :3] - tr.x[k - 1, :3]) < 0.1
    # the detector finds nothing: a predict-only step
    state, rec = step(state, tr, k, chaser, StubDetector(FrameDetection.missing(np.zeros(3))), setup)
    assert finite(state) and state.t_s == tr.t_s[k] and state.n_meas[0] == 0 and rec.hypothesis == -1
    assert rec.converged and rec.roi_px is not None and rec.coarse_fallback  # ROI found too little: coarse pass
    # one wrong corner (60 px off) among right ones: the gate rejects it, the rest are used
    k += 1
    d = truth_detection(tr, k)
    j = int(np.flatnonzero(d.visible)[0])
    wrong = d.corners_px.copy()
    wrong[j] += (60.0, -45.0)
    state, rec = step(state, tr, k, chaser, StubDetector(detection(wrong, d.visible)), setup)
    assert finite(state) and state.rejected[0] >= 1 and state.n_meas[0] == d.visible.sum() - 1
    assert np.linalg.norm(state.mean[0, :3] - tr.x[k, :3]) < 0.1
    # garbage: 8 random points over the whole image, then NaN positions flagged as found
    k += 1
    rng = np.random.default_rng(3)
    state, rec = step(state, tr, k, chaser, StubDetector(detection(rng.uniform(0, 1024, (8, 2)), np.ones(8, bool))),
                      setup)
    assert finite(state) and state.n_meas[0] == 0
    k += 1
    nan_det = FrameDetection(np.full((8, 2), np.nan), np.full((8, 2, 2), np.nan), np.ones(8), np.ones(8, bool),
                             np.full((8, 2), np.nan), 0.0, False, np.zeros(3), np.zeros((0, 2)))
    state, rec = step(state, tr, k, chaser, StubDetector(nan_det), setup)
    assert finite(state) and state.n_meas[0] == 0 and rec.hypothesis == -1
    # and the loop carries on with good detections
    for k in range(k + 1, k + 10):
        state, rec = step(state, tr, k, chaser, StubDetector(truth_detection(tr, k)), setup)
    assert finite(state) and np.linalg.norm(state.mean[0, :3] - tr.x[k, :3]) < 0.1


def test_a_frame_in_eclipse_is_skipped(truth_600, setup_and_chaser):
    tr = truth_600
    setup, chaser = setup_and_chaser
    state = start(tr, setup, chaser)
    stub = StubDetector(truth_detection(tr, 1))
    new, rec = step(state, tr, 1, chaser, stub, setup, image=None)
    assert stub.calls == [] and rec.skipped and rec.detection is None and rec.hypothesis == -1
    assert new.t_s == tr.t_s[1] and new.n_meas[0] == 0 and finite(new)
    assert np.trace(new.cov[0]) > np.trace(state.cov[0]) - 1e-12  # predicted only: no information came in


def test_the_prior_decides_the_half_turn(truth_600, setup_and_chaser):
    tr = truth_600
    setup, chaser = setup_and_chaser
    # before convergence (P0: 1 m, ~10 deg): the detector's naming is the half-turn, its alternative the truth
    state = start(tr, setup, chaser, seed=1)
    right = tr.corners_px[1]
    vis = tr.visible[1] & tr.in_frame[1]
    turned = detection(right[loop.HALF_TURN], vis[loop.HALF_TURN], alt=np.where(vis[:, None], right, np.nan),
                       ambiguous=True)
    new, rec = step(state, tr, 1, chaser, StubDetector(turned), setup)
    assert not rec.converged and rec.hypothesis == 1 and rec.costs[0] - rec.costs[1] > loop.LoopConfig().decisive_cost
    assert new.n_meas[0] == vis.sum()
    # a prior that cannot tell (attitude sigma ~90 deg): the ambiguous frame is not used, both stay open
    P0 = np.diag(np.repeat(np.square([1.0, 0.01, 0.5, 1.7e-3]), 3))
    state = start(tr, setup, chaser, seed=2, P0=P0)
    sym = detection(right, vis, alt=np.where(vis[:, None], right[loop.HALF_TURN], np.nan), ambiguous=True)
    new, rec = step(state, tr, 1, chaser, StubDetector(sym), setup)
    if abs(rec.costs[0] - rec.costs[1]) < loop.LoopConfig().decisive_cost:
        assert rec.hypothesis == -1 and new.n_meas[0] == 0
    else:
        assert rec.hypothesis == int(np.argmin(rec.costs))
    # after convergence the ROI comes from the prediction and holds every predicted corner
    state = converged_state(tr, setup, chaser)
    stub = StubDetector(turned)
    k = 40
    d = truth_detection(tr, k)
    turned = detection(d.corners_px[loop.HALF_TURN], d.visible[loop.HALF_TURN],
                       alt=np.where(d.visible[:, None], d.corners_px, np.nan), ambiguous=True)
    stub = StubDetector(turned)
    new, rec = step(state, tr, k, chaser, stub, setup)
    assert rec.converged and rec.hypothesis == 1 and stub.calls[0]["prior"] is not None
    x0, y0, side = stub.calls[0]["roi_px"]
    c = tr.corners_px[k][tr.in_frame[k]]
    assert np.all(c >= (x0, y0)) and np.all(c <= (x0 + side, y0 + side))


def run_cfg(weights, **over):
    from envisat_pose.app.scenarios import job_defaults

    data = {"scenario": "default", "duration_s": 4.0, "weights": weights, "workers": 1,
            "filter": {**loop.LOOP_FILTER, **job_defaults("default")["filter"]}}
    data.update(over)
    loop._stage_types()
    from envisat_pose.config import from_dict

    return loop.finish_config(from_dict(loop.RunConfig, data))


def test_a_short_closed_loop_writes_every_output(tmp_path, detector_weights):
    from envisat_pose.analysis.recording import read_recording
    from envisat_pose.contracts import Detections, Estimates, TruthTrajectory

    out = tmp_path / "run"
    summary = loop.run_closed_loop(run_cfg(detector_weights), str(out), progress=False)
    names = {"truth.npz", "est.npz", "det.npz", "errors.png", "run.config.toml", "summary.json", "recording.rrd"}
    assert names <= set(os.listdir(out))
    est = Estimates.load(str(out / "est.npz"))
    truth = TruthTrajectory.load(str(out / "truth.npz"))
    det = Detections.load(str(out / "det.npz"))
    T = 5
    assert est.x_hat.shape == (1, T, 12) and np.isfinite(est.x_hat).all() and len(det.t_s) == T
    np.testing.assert_array_equal(est.x_true[0], truth.x)
    with np.load(out / "det.npz", allow_pickle=False) as z:
        for key in ("key", "alt_corners_px", "alt_probability", "ambiguous", "roi_px", "hypothesis", "skipped"):
            assert key in z.files and len(z[key]) == T
    cfg = tomllib.loads((out / "run.config.toml").read_text())
    assert cfg["scenario"] == "default" and cfg["image"]["mode"] == "sequence" and cfg["loop"]["roi"] is True
    assert json.loads((out / "summary.json").read_text())["frames"] == T == summary["frames"]
    # `envisat view RUN_DIR` opens this recording
    from envisat_pose.app.view import recordings

    assert recordings(str(out)) == [str(out / "recording.rrd")]
    # the recording, read back with Rerun's reader
    static, temporal = read_recording(out / "recording.rrd")
    for entity in ("/world/target", "/world/target_est", "/world/target_est/position_3sigma",
                   "/world/chaser/camera/image", "/world/chaser/camera/image/corners_true",
                   "/world/chaser/camera/image/corners_detected", "/metrics/error/position_m/x",
                   "/metrics/error/attitude_deg/z"):
        assert entity in temporal, entity
    assert "/world/chaser/camera" in static and "/world" in static
    img = temporal["/world/chaser/camera/image"]
    assert img["frame"] == list(range(T))  # one image per frame
    blobs = img["EncodedImage:blob"]
    assert all(bytes(np.asarray(b[0], np.uint8)[:2]) == b"\xff\xd8" for b in blobs)  # JPEG
    media = [m[0] for m in img["EncodedImage:media_type"] if m]
    assert media and set(media) == {"image/jpeg"}
    tr_est = temporal["/world/target_est"]
    xyz = np.array([t[0] for t in tr_est["Transform3D:translation"]])
    np.testing.assert_allclose(xyz, est.x_hat[0, :, 0:3], rtol=0, atol=1e-4)  # float32 in the recording
    ex = np.array([v[0] for v in temporal["/metrics/error/position_m/x"]["Scalars:scalars"]])
    np.testing.assert_allclose(ex, est.x_hat[0, :, 0] - est.x_true[0, :, 0], atol=1e-9)
    d = temporal["/world/chaser/camera/image/corners_detected"]
    n_det = [len(p) if p is not None else 0 for p in d["Points2D:positions"]]
    assert n_det == det.visible.sum(axis=1).tolist()


def test_frames_in_the_earths_shadow_are_skipped(tmp_path, detector_weights):
    """The sun straight behind the Earth: the chaser is in its shadow all along; nothing is rendered or detected,
    the filter predicts, and the recording holds no image."""
    from envisat_pose.analysis.recording import read_recording
    from envisat_pose.contracts import Estimates
    from envisat_pose.datagen.orbit import chaser_orbit
    from envisat_pose.datagen.scenario import scenario_config

    r0 = chaser_orbit(scenario_config("default").orbit, np.array([0.0])).r_N_m[0]
    cfg = run_cfg(detector_weights, duration_s=3.0, image={"sun_dir": (-r0 / np.linalg.norm(r0)).tolist()})
    out = tmp_path / "dark"
    summary = loop.run_closed_loop(cfg, str(out), progress=False)
    assert summary["run0"]["frames_skipped_eclipse"] == 4
    est = Estimates.load(str(out / "est.npz"))
    assert np.isfinite(est.x_hat).all() and (est.n_meas == 0).all()
    with np.load(out / "det.npz", allow_pickle=False) as z:
        assert z["skipped"].all() and not z["visible"].any()
    _, temporal = read_recording(out / "recording.rrd")
    assert "/world/chaser/camera/image" not in temporal


@pytest.mark.slow
def test_the_closed_loop_converges_on_the_default_scenario(tmp_path, detector_weights):
    """Pixels from the detector on rendered frames: under 10 cm and 2 deg from 5 minutes on."""
    cfg = run_cfg(detector_weights, duration_s=330.0)
    summary = loop.run_closed_loop(cfg, str(tmp_path / "conv"), progress=False)
    from envisat_pose.attitude import mrp_error_angle_rad
    from envisat_pose.contracts import Estimates

    est = Estimates.load(str(tmp_path / "conv" / "est.npz"))
    late = est.t_s >= 300.0
    pos = np.linalg.norm(est.x_hat[0, late, :3] - est.x_true[0, late, :3], axis=-1)
    ang = np.degrees(mrp_error_angle_rad(est.x_hat[0, late, 6:9], est.x_true[0, late, 6:9]))
    assert pos.max() < 0.10, (pos.max(), summary["run0"])
    assert ang.max() < 2.0, (ang.max(), summary["run0"])
    assert not est.diverged.any()


def test_the_cli_runs_several_loops_in_parallel(tmp_path, detector_weights, capsys):
    """`envisat run --runs 2`: two closed loops on one truth through the core's runner (two processes), each
    from its own initial estimate; the error table is printed."""
    from envisat_pose.app.cli import main
    from envisat_pose.contracts import Estimates

    out = tmp_path / "two"
    assert main(["run", "--scenario", "default", "--duration-s", "2", "--runs", "2", "--workers", "2", "--weights",
                 detector_weights, "--seed", "5", "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "position" in printed and "attitude" in printed and "real-time factor" in printed
    est = Estimates.load(str(out / "est.npz"))
    assert est.x_hat.shape == (2, 3, 12) and np.isfinite(est.x_hat).all()
    np.testing.assert_array_equal(est.x_true[0], est.x_true[1])
    assert not np.allclose(est.x_hat[0, 0], est.x_hat[1, 0])  # different initial estimates
    assert json.loads(est.config_json)["run"]["runs"] == 2
    # a bad flag is one line, before any work
    assert main(["run", "--scenario", "nope", "--out", str(tmp_path / "x"), "--weights", detector_weights]) == 2
    assert "scenario" in capsys.readouterr().err and not (tmp_path / "x").exists()
