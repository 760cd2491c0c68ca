"""`envisat run`, the online closed loop on the Tracker: the whole loop with the real renderer, detector and
filter (outputs, the recording read back with Rerun's reader, eclipse, --warm-start, --runs 2) and a cold start on
the default scenario that converges."""

import dataclasses
import json
import os
import tomllib

import numpy as np
import pytest

from envisat_pose.pipelines.runs import closed_loop as loop


def run_cfg(weights, duration_s=4.0, **flags):
    """The default scenario's run as `envisat run` resolves it (pipelines.jobs.resolve_job), with flags over it."""
    from envisat_pose.pipelines.jobs import resolve_job

    return resolve_job("run", "default", overrides={"duration_s": duration_s, "weights": weights, "workers": 1,
                                                    **flags})


def test_a_short_closed_loop_writes_every_output(tmp_path, detector_weights, verify_rrd):
    from envisat_pose.analysis.recording import read_recording
    from envisat_pose.contracts import Detections, Estimates, TruthTrajectory

    out = tmp_path / "run"
    summary = loop.run_closed_loop(run_cfg(detector_weights, warm_start=True), str(out), progress=False)
    names = {"truth.npz", "est.npz", "det.npz", "errors.png", "run.config.toml", "summary.json", "recording.rrd"}
    assert names <= set(os.listdir(out))
    est = Estimates.load(str(out / "est.npz"))
    truth = TruthTrajectory.load(str(out / "truth.npz"))
    det = Detections.load(str(out / "det.npz"))
    T = 5
    assert est.x_hat.shape == (1, T, 12) and len(det.t_s) == T
    # warm: the prior still earns its claim: "acquiring" (no estimate: NaN) until confirmed by confirm_frames (5)
    # frames of its own innovations, then tracking
    assert est.status[0].tolist() == [0, 0, 0, 0, 1], est.status
    assert est.diverged.tolist() == [False]  # no frame lost (test_diverged_... loses one)
    assert np.isnan(est.x_hat[0, :4]).all() and np.isfinite(est.x_hat[0, 4]).all()
    np.testing.assert_array_equal(est.x_true[0], truth.x)
    with np.load(out / "det.npz", allow_pickle=False) as z:
        for key in ("key", "alt_corners_px", "alt_probability", "ambiguous", "roi_px", "naming", "status", "skipped"):
            assert key in z.files and len(z[key]) == T
        assert z["status"].tolist() == [0, 0, 0, 0, 1]
        # which target det.npz holds, as `envisat track` records it: ENVISAT's too
        assert json.loads(str(z["config_json"]))["target"]["name"] == "envisat"
    assert json.loads(est.config_json)["target"]["keypoint_names"] == list("ABCDEFGH")
    cfg = tomllib.loads((out / "run.config.toml").read_text())
    assert cfg["scenario"] == "default" and cfg["image"]["mode"] == "sequence"
    assert cfg["tracker"]["roi"]["enabled"] is True
    assert json.loads((out / "summary.json").read_text())["frames"] == T == summary["frames"]
    # what `envisat track` says without a truth, said here too: from est.npz's own columns
    with np.load(out / "est.npz", allow_pickle=False) as z:
        nis, dof = z["nis"][0], z["nis_dof"][0]
    assert summary["frames_by_status"] == summary["run0"]["frames_by_status"] == {
        "acquiring": 4, "tracking": 1, "lost": 0, "coasting": 0}
    assert summary["run0"]["first_tracking_s"] == float(est.t_s[4]) and summary["run0"]["final_status"] == "tracking"
    assert dof.sum() > 0 and summary["mean_nis_per_dof"] == pytest.approx(nis.sum() / dof.sum(), rel=1e-12)
    from envisat_pose.analysis.viewer import recordings

    assert recordings(str(out)) == [str(out / "recording.rrd")]
    verify_rrd(out / "recording.rrd")  # footer written: `rerun rrd verify` passes
    static, temporal = read_recording(out / "recording.rrd")
    for entity in ("/world/target", "/world/target_est", "/world/target_est/position_3sigma",
                   "/world/chaser/camera/image", "/world/chaser/camera/image/keypoints_true",
                   "/world/chaser/camera/image/keypoints_detected", "/world/chaser/camera/image/keypoints_estimated",
                   "/metrics/error/position_m/x", "/metrics/error/attitude_deg/z", "/metrics/nees/value",
                   "/metrics/nis", "/metrics/tracker/status", "/metrics/tracker/p_best"):
        assert entity in temporal, entity
    assert "/world/chaser/camera" in static and "/world" in static
    img = temporal["/world/chaser/camera/image"]
    assert img["frame"] == list(range(T))
    assert all(bytes(np.asarray(b[0], np.uint8)[:2]) == b"\xff\xd8" for b in img["EncodedImage:blob"])  # JPEG
    xyz = np.array([t[0] for t in temporal["/world/target_est"]["Transform3D:translation"]])
    shown = est.status[0] == 1  # the estimate is drawn on the rows that hold one (here: tracking)
    np.testing.assert_allclose(xyz, est.x_hat[0, shown, 0:3], rtol=0, atol=1e-4)  # float32 in the recording
    ex = np.array([v[0] for v in temporal["/metrics/error/position_m/x"]["Scalars:scalars"]])
    np.testing.assert_allclose(ex, est.x_hat[0, shown, 0] - est.x_true[0, shown, 0], atol=1e-9)
    # the band named as an estimate's (.../<axis>/filter_3sigma): +-3 sqrt(P_xx) of the rows shown
    band = np.array(temporal["/metrics/error/position_m/x/filter_3sigma"]["Scalars:scalars"])
    np.testing.assert_allclose(band, 3 * np.sqrt(est.P[0, shown, 0, 0])[:, None] * [1, -1], rtol=1e-6)
    nis_rows = shown & (dof > 0)  # the tracker's NIS per dof beside the truth's NEES, on the frames with both
    logged = np.array([v[0] for v in temporal["/metrics/nis"]["Scalars:scalars"]])
    np.testing.assert_allclose(logged, nis[nis_rows] / dof[nis_rows], rtol=1e-6)
    d = temporal["/world/chaser/camera/image/keypoints_detected"]
    n_det = [len(p) if p is not None else 0 for p in d["Points2D:positions"]]
    assert n_det == det.visible.sum(axis=1).tolist()


def test_frames_in_the_earths_shadow_are_skipped(tmp_path, detector_weights):
    """The sun straight behind the Earth: the chaser is in its shadow all along; nothing is rendered or detected,
    the tracker stays acquiring, and the recording holds no image."""
    from envisat_pose.analysis.recording import read_recording
    from envisat_pose.contracts import Estimates
    from envisat_pose.datagen.orbit import chaser_orbit
    from envisat_pose.datagen.scenario import scenario_config

    r0 = chaser_orbit(scenario_config("default").orbit, np.array([0.0])).r_N_m[0]
    cfg = run_cfg(detector_weights, duration_s=3.0, **{"image.sun_dir": (-r0 / np.linalg.norm(r0)).tolist()})
    out = tmp_path / "dark"
    summary = loop.run_closed_loop(cfg, str(out), progress=False)
    assert summary["run0"]["frames_skipped_eclipse"] == 4 and summary["run0"]["frames_acquiring"] == 4
    est = Estimates.load(str(out / "est.npz"))
    # no estimate exists: every row says so (status acquiring, code 0 in the stored legend) and holds NaN, not a
    # made-up state
    assert (est.status == 0).all() and np.isnan(est.x_hat).all() and np.isnan(est.P).all()
    assert (est.n_meas == 0).all()
    with np.load(out / "est.npz", allow_pickle=False) as z:
        assert json.loads(str(z["status_legend"]))["0"]["name"] == "acquiring"
    with np.load(out / "det.npz", allow_pickle=False) as z:
        assert z["skipped"].all() and not z["visible"].any()
        assert json.loads(str(z["status_legend"]))["1"]["name"] == "tracking"
    _, temporal = read_recording(out / "recording.rrd")
    assert "/world/chaser/camera/image" not in temporal


@pytest.mark.slow
def test_the_closed_loop_starts_cold_and_converges_on_the_default_scenario(tmp_path, detector_weights):
    """Rendered frames, the shipped detector, no prior: the first declared tracking is correct and comes within
    60 s of the first frame, no frame is claimed while wrong (5 deg, 2 % of range), and over every frame from the
    first tracking on the filter is consistent (mean NEES near 12, few frames beyond the 99.9 % quantile) with a
    range bias inside its floor (1 cm at 50 m, with the detector's measured scale bias of ~1e-3 allowed: 5 cm)."""
    cfg = run_cfg(detector_weights, duration_s=200.0)
    summary = loop.run_closed_loop(cfg, str(tmp_path / "conv"), progress=False)
    s = summary["scores"]
    assert s["runs_tracked"] == 1 and s["first_track_correct"] == 1, s
    assert s["time_to_first_correct_track_s"]["max"] <= 60.0, s
    assert s["false_lock_s"] == 0.0, s
    sc = s["scored"]
    assert 6.0 < sc["mean_nees"] < 24.0 and sc["nees_tail_share"] < 0.05, sc
    assert abs(sc["range_bias_m"]) < 0.05, sc


def test_the_cli_runs_several_loops_in_parallel(tmp_path, detector_weights, capsys):
    """`envisat run --runs 2 --warm-start`: two closed loops on one truth through the core's runner (two
    processes), each from its own initial estimate; the score table is printed, and the bar counted the two runs'
    frames to its end (it counted whole runs)."""
    from envisat_pose.app.cli import main
    from envisat_pose.contracts import Estimates

    out = tmp_path / "two"
    assert main(["run", "--scenario", "default", "--duration-s", "5", "--runs", "2", "--workers", "2", "--weights",
                 detector_weights, "--seed", "5", "--warm-start", "--out", str(out)]) == 0
    printed, err = capsys.readouterr()
    assert "false-lock time" in printed and "NEES" in printed and "real-time factor" in printed
    last = [line for line in err.replace("\r", "\n").splitlines() if line.startswith("closed loop")][-1]
    assert "100%" in last and "12/12" in last and "frame" in last, err
    est = Estimates.load(str(out / "est.npz"))
    # each warm start earns its claim over confirm_frames (5) frames, then tracks
    assert est.x_hat.shape == (2, 6, 12) and (est.status[:, -1] == 1).all() and np.isfinite(est.x_hat[:, -1]).all()
    np.testing.assert_array_equal(est.x_true[0], est.x_true[1])
    assert not np.allclose(est.x_hat[0, -1], est.x_hat[1, -1])  # different initial estimates
    assert json.loads(est.config_json)["run"]["runs"] == 2
    # a bad flag is one line, before any work
    assert main(["run", "--scenario", "nope", "--out", str(tmp_path / "x"), "--weights", detector_weights]) == 2
    assert "scenario" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_a_run_that_never_tracks_says_so(tmp_path, detector_weights, capsys):
    """A cold start of 4 frames (the cold start needs 20): nothing tracked, said in one line as `envisat track` says
    it, and the summary's second-half errors are None (est.npz holds no estimate), not the placeholder state's."""
    from envisat_pose.app.cli import main

    out = tmp_path / "short"
    assert main(["run", "--scenario", "default", "--duration-s", "3", "--weights", detector_weights, "--out", str(out),
                 "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "nothing tracked (4 acquiring)" in printed, printed
    errors = json.loads((out / "summary.json").read_text())["scores"]["errors"]
    assert errors["position_m"]["rms_after"] is None and errors["attitude_deg"]["final"] is None
    assert main(["demo", "--duration-s", "3", "--out", str(tmp_path / "demo"), "--quiet"]) == 0  # demo says so too
    printed = capsys.readouterr().out
    assert "nothing tracked (4 acquiring)" in printed
    assert "weights models/detector.safetensors" in printed, printed  # as its outputs record them: no machine path


def test_a_run_config_a_user_builds_is_the_verbs_job(tmp_path, detector_weights):
    """A RunConfig is complete when built (the image's sequence fields and sun, the scenario's duration, rate and
    filter): one built from a dict without the scenario's layer, the plain constructor's and the verb's
    resolution (pipelines.jobs.resolve_job) are one config, and it runs as it is."""
    from envisat_pose.config import resolve_job_config
    from envisat_pose.pipelines.jobs import resolve_job
    from envisat_pose.pipelines.runs.run_config import RunConfig

    fields = {"duration_s": 2.0, "weights": detector_weights, "workers": 1, "warm_start": True}
    raw = resolve_job_config(RunConfig, {}, None, {"scenario": "default", **fields})
    assert raw == RunConfig(scenario="default", **fields) == resolve_job("run", "default", **fields)
    assert raw.image.sun_dir is not None and raw.image.num_images == 3 and raw.image.sequence.scenario == "default"
    a = loop.run_closed_loop(raw, str(tmp_path / "raw"), progress=False)
    assert a["frames"] == 3
    with np.load(tmp_path / "raw" / "est.npz") as za:
        assert za["x_true"].shape == (1, 3, 12)


def test_diverged_means_the_runs_own_monitor_flagged_it(tmp_path, detector_weights):
    """Estimates.diverged has one meaning (contracts.py): for tracker runs, a frame declared lost; whether a run
    met the truth's tolerances is stored apart (`settled`). A warm start drawn from a P0 far too wide for the
    filter (an attitude sigma of 1 per MRP component: rotations of order 180 deg) is contradicted by the rendered frames' corners: the
    tracker declares the frame lost, drops its estimate and acquires again, and the run is diverged (the tight
    warm start of the first test loses nothing: diverged False there)."""
    out = tmp_path / "d"
    cfg = run_cfg(detector_weights, duration_s=3.0, warm_start=True,
                  **{"filter.p0_sigma": [1.0, 0.01, 1.0, 1.7e-3]})
    summary = loop.run_closed_loop(cfg, str(out), progress=False)
    with np.load(out / "est.npz", allow_pickle=False) as z:
        lost = z["status"][0] == 2
        assert lost.any(), z["status"]
        assert z["diverged"].tolist() == [True]
        assert summary["run0"]["frames_lost"] == int(lost.sum())
        k = int(np.argmax(lost))
        # dropped: no estimate from the lost frame on until a new bank is confirmed (not within 3 s)
        assert np.isnan(z["x_hat"][0, k:]).all() and (z["status"][0, k + 1:] == 0).all(), z["status"]
        assert z["settled"].tolist() == [False]


def test_a_run_at_another_size_says_which_pixels_are_whose(tmp_path, detector_weights):
    """At [image] resolution_px 128, det.npz's pixels are the 128-px frames' (its config_json's camera, est.npz's
    too) and truth.npz's corners_px the MJCF chaser_cam's 1024 px (the truth's contract): the documented scaling
    (u + 0.5) s - 0.5 takes the truth's onto the frames', checked against the keypoints in C projected here through
    the recorded camera."""
    from envisat_pose.contracts import TruthTrajectory
    from envisat_pose.geometry import load_camera

    out = tmp_path / "run"
    loop.run_closed_loop(run_cfg(detector_weights, duration_s=1.0, **{"image.resolution_px": 128}), str(out))
    with np.load(out / "det.npz", allow_pickle=False) as z:
        cam = json.loads(str(z["config_json"]))["camera"]
    with np.load(out / "est.npz", allow_pickle=False) as z:
        assert json.loads(str(z["config_json"]))["camera"] == cam
    assert (cam["width_px"], cam["height_px"]) == (128, 128) and cam["cx_px"] == cam["cy_px"] == 63.5
    truth = TruthTrajectory.load(str(out / "truth.npz"))
    R = load_camera().R_K_from_C
    p = truth.corners_C_m @ R.T  # (T, K, 3) in the camera frame
    uv = cam["f_px"] * p[..., :2] / p[..., 2:] + [cam["cx_px"], cam["cy_px"]]
    s = cam["width_px"] / load_camera().width_px
    np.testing.assert_allclose((truth.corners_px + 0.5) * s - 0.5, uv, rtol=0, atol=1e-6)


def test_an_interrupted_run_leaves_no_folder_it_made(tmp_path, detector_weights, monkeypatch):
    """Ctrl-C in a run into a new folder (parents too) removes what it made, when empty; a folder that was there
    stays, with what it held (an earlier run's outputs)."""
    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(loop, "_run_closed_loop", stop)
    with pytest.raises(KeyboardInterrupt):
        loop.run_closed_loop(run_cfg(detector_weights), str(tmp_path / "new" / "run"))
    assert os.listdir(tmp_path) == []
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "summary.json").write_text("{}")
    (tmp_path / "old" / "run.config.toml").write_text("# envisat run: an earlier run's\n")  # so the run's own
    with pytest.raises(KeyboardInterrupt):
        loop.run_closed_loop(run_cfg(detector_weights), str(tmp_path / "old"))
    assert sorted(os.listdir(tmp_path / "old")) == ["run.config.toml", "summary.json"]


def test_a_config_files_scenario_is_the_runs_unless_the_flag_says_another(tmp_path):
    """run.config.toml records the scenario: given back with --config it is the run's (the flag's default,
    'default', once overrode it without a word, so the written config did not reproduce a stress-tumble run);
    --scenario typed still wins."""
    from envisat_pose.app.cli import build_parser
    from envisat_pose.app.run import resolve_config
    from envisat_pose.config import to_dict, to_toml
    from envisat_pose.pipelines.jobs import resolve_job

    written = tmp_path / "run.config.toml"
    written.write_text(to_toml(to_dict(resolve_job("run", "stress-tumble", duration_s=5.0))))
    parse = build_parser().parse_args
    cfg = resolve_config(parse(["run", "--config", str(written), "--out", "x"]))
    assert cfg.scenario == "stress-tumble" and cfg == resolve_job("run", "stress-tumble", duration_s=5.0)
    assert resolve_config(parse(["run", "--config", str(written), "--scenario", "slow-tumble", "--out", "x"])
                          ).scenario == "slow-tumble"
    assert resolve_config(parse(["run", "--out", "x"])).scenario == "default"


def test_the_run_records_the_processes_it_used_and_the_recordings_size(tmp_path):
    """`--runs 1 --workers 4` runs one process and its run.config.toml says 1 (it said 4); the summary's
    recording_bytes is the size of the file a 'save:PATH' sink wrote wherever PATH is (it counted the run folder's
    recording.rrd only: 0 for a recording saved elsewhere), and 0 for a live viewer's sink."""
    from envisat_pose.pipelines.runs.run_config import RunConfig

    assert RunConfig(runs=1, workers=4).workers == 1 and RunConfig(runs=3, workers=2).workers == 2
    # the processes not given follow a replace's runs (one process stayed for 8 runs)
    assert dataclasses.replace(RunConfig(runs=1), runs=8).workers == RunConfig(runs=8).workers
    assert dataclasses.replace(RunConfig(runs=8, workers=2), runs=4).workers == 2
    rrd = tmp_path / "elsewhere" / "mine.rrd"
    rrd.parent.mkdir()
    rrd.write_bytes(b"x" * 1234)
    assert loop.saved_bytes(f"save:{rrd}") == 1234
    assert loop.saved_bytes("spawn") == 0 and loop.saved_bytes(f"save:{tmp_path / 'none.rrd'}") == 0
