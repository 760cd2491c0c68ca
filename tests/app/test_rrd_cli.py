"""Every `--rrd` verb writes a recording that Rerun's own reader reads back, with the design's entity paths and
timelines and the values of the arrays it came from (run.npz, est.npz, campaign.npz, the dataset's labels), and
that `rerun rrd verify` passes (footer included)."""

import os

import numpy as np
import pytest

from envisat_pose.analysis.recording import read_recording as read_rrd
from envisat_pose.app.cli import main
from envisat_pose.contracts import Estimates, TruthTrajectory
from envisat_pose.geometry import CORNER_NAMES, EDGES, load_camera

os.environ.setdefault("MUJOCO_GL", "osmesa")


def check_model(static):
    """The static scene: annotation context A-H with the 12 edges, the pinhole of load_camera, the target's mesh."""
    ctx = static["/world"]["AnnotationContext:context"][0][0]["class_description"]
    assert [k["label"] for k in ctx["keypoint_annotations"]] == list(CORNER_NAMES)
    assert sorted((c["keypoint0"], c["keypoint1"]) for c in ctx["keypoint_connections"]) == sorted(
        tuple(sorted(e)) for e in EDGES)
    K = static["/world/chaser/camera"]["Pinhole:image_from_camera"][0]
    assert K[0] == pytest.approx(load_camera().f_px) and K[4] == pytest.approx(load_camera().f_px)
    assert "Mesh3D:vertex_positions" in static["/world/target/model"]


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    out, rrd = d / "run.npz", d / "run.rrd"
    assert main(["simulate", "--duration-s", "40", "--dt-s", "2", "--seed", "5", "--out", str(out), "--rrd", str(rrd),
                 "--quiet"]) == 0
    return out, rrd


def test_simulate_rrd(simulated, verify_rrd):
    out, rrd = simulated
    tr = TruthTrajectory.load(str(out))
    verify_rrd(rrd)
    static, temporal = read_rrd(rrd)
    check_model(static)
    N = len(tr.t_s)
    assert N == 21
    for entity in ("/world/target", "/world/keypoints_true", "/world/chaser/camera/image/keypoints_true",
                   "/metrics/visible_keypoints"):
        assert temporal[entity]["frame"] == list(range(N))
        np.testing.assert_allclose([d.total_seconds() for d in temporal[entity]["sim_time"]], tr.t_s)
    for k in (0, 7, N - 1):
        np.testing.assert_allclose(temporal["/world/keypoints_true"]["Points3D:positions"][k], tr.corners_C_m[k],
                                   rtol=1e-6, atol=1e-5)
        np.testing.assert_allclose(temporal["/world/target"]["Transform3D:translation"][k][0], tr.x[k, :3], rtol=1e-6)
    np.testing.assert_array_equal([v[0] for v in temporal["/metrics/in_frame_keypoints"]["Scalars:scalars"]],
                                  tr.in_frame.sum(axis=1))


def test_estimate_rrd(simulated, tmp_path, verify_rrd):
    truth, _ = simulated
    out, rrd = tmp_path / "est.npz", tmp_path / "est.rrd"
    assert main(["estimate", "--truth", str(truth), "--runs", "3", "--rate-hz", "0.5", "--seed", "2", "--out", str(out),
                 "--rrd", str(rrd), "--quiet"]) == 0
    est = Estimates.load(str(out))
    tr = TruthTrajectory.load(str(truth))
    verify_rrd(rrd)
    static, temporal = read_rrd(rrd)
    check_model(static)
    T = len(est.t_s)
    assert "LineStrips3D:strips" in static["/world/target_est/model"]
    for entity in ("/world/target", "/world/target_est", "/world/target_est/position_3sigma",
                   "/metrics/error/position_m/x", "/metrics/error/attitude_deg/y/filter_3sigma"):
        assert temporal[entity]["frame"] == list(range(T)), entity
    np.testing.assert_allclose([v[0] for v in temporal["/world/target_est"]["Transform3D:translation"]],
                               est.x_hat[0, :, :3], rtol=1e-6)
    # the truth's corners at the filter's steps (every truth sample here: 0.5 Hz on a 2 s truth)
    np.testing.assert_allclose(temporal["/world/keypoints_true"]["Points3D:positions"][5], tr.corners_C_m[5], rtol=1e-6,
                               atol=1e-5)
    # every run's error, and the filter's band
    err = np.array(temporal["/metrics/error/position_m/z"]["Scalars:scalars"])
    np.testing.assert_allclose(err, (est.x_hat - est.x_true)[:, :, 2].T, atol=1e-12)
    band = np.array(temporal["/metrics/error/position_m/z/filter_3sigma"]["Scalars:scalars"])
    np.testing.assert_allclose(band[:, 0], 3 * np.sqrt(est.P[:, :, 2, 2].mean(axis=0)), rtol=1e-12)
    half = np.array([v[0] for v in temporal["/world/target_est/position_3sigma"]["Ellipsoids3D:half_sizes"]])
    np.testing.assert_allclose(np.sort(half**2, axis=1), 9 * np.linalg.eigvalsh(est.P[0, :, :3, :3]), rtol=1e-4)


def test_montecarlo_rrd(tmp_path, verify_rrd, capsys):
    out, rrd = tmp_path / "mc", tmp_path / "mc.rrd"
    assert main(["montecarlo", "--scenario", "default", "--duration-s", "40", "--runs", "5", "--block-runs", "2",
                 "--seed", "3", "--out", str(out), "--rrd", str(rrd), "--quiet"]) == 0
    said = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith(f"wrote {rrd}")]
    assert len(said) == 1 and "of envisat over 41 steps: the truth, run 0's estimate" in said[0] \
        and "the errors of 5 runs" in said[0] and "mean NEES" in said[0], said  # the line says what is in it
    with np.load(out / "campaign.npz") as z:
        sample_err, filt, t_s = z["sample_err"], z["filter_3sigma"], z["t_s"]
        nees_mean, nees_bounds = z["nees_mean"], z["nees_bounds"]
    verify_rrd(rrd)
    static, temporal = read_rrd(rrd)
    check_model(static)
    T = len(t_s)
    assert sample_err.shape[0] == 5
    err = np.array(temporal["/metrics/error/velocity_m_s/x"]["Scalars:scalars"])
    np.testing.assert_allclose(err, sample_err[:, :, 3].T, atol=1e-12)
    band = np.array(temporal["/metrics/error/angular_velocity_deg_s/z/filter_3sigma"]["Scalars:scalars"])
    np.testing.assert_allclose(band[:, 0], np.degrees(filt[:, 11]), rtol=1e-12)
    # run 0 filtered again for its pose and ellipsoid is the campaign's run 0
    truth_x = np.array([v[0] for v in temporal["/world/target"]["Transform3D:translation"]])
    est_x = np.array([v[0] for v in temporal["/world/target_est"]["Transform3D:translation"]])
    assert len(est_x) == T
    np.testing.assert_allclose(est_x - truth_x, sample_err[0, :, 0:3], atol=1e-5)  # float32 positions at 50 m
    # the campaign's mean NEES over its 5 runs and its band, as nees_nis.png draws them (not run 0's alone)
    assert static["/metrics/nees/value"]["SeriesLines:names"] == ["mean NEES over 5 runs"]
    np.testing.assert_allclose([v[0] for v in temporal["/metrics/nees/value"]["Scalars:scalars"]], nees_mean,
                               rtol=1e-12)
    np.testing.assert_allclose(temporal["/metrics/nees/band"]["Scalars:scalars"], np.tile(nees_bounds, (T, 1)))


def test_estimate_rrd_nees_is_the_filters_own_charts(simulated, tmp_path):
    """The recording's NEES is the one the summary line gives: in the filter's chart of the sigma points (here
    'rotation'), not the additive chart's."""
    from envisat_pose.filtering.estimator import nees

    truth, _ = simulated
    out, rrd, cfg = tmp_path / "est.npz", tmp_path / "est.rrd", tmp_path / "est.toml"
    cfg.write_text('[filter]\nsigma_chart = "rotation"\n')
    assert main(["estimate", "--truth", str(truth), "--config", str(cfg), "--runs", "2", "--rate-hz", "0.5",
                 "--out", str(out), "--rrd", str(rrd), "--quiet"]) == 0
    est = Estimates.load(str(out))
    _, temporal = read_rrd(rrd)
    logged = np.array([v[0] for v in temporal["/metrics/nees/value"]["Scalars:scalars"]])
    np.testing.assert_allclose(logged, nees(est.x_true, est.x_hat, est.P, "rotation").mean(axis=0), rtol=1e-9)
    additive = nees(est.x_true, est.x_hat, est.P, "additive").mean(axis=0)
    assert np.abs(logged - additive).max() > 1e-6 * np.abs(additive).max()


def test_montecarlo_rrd_refuses_a_sweep_before_work(tmp_path, capsys):
    rc = main(["montecarlo", "--scenario", "default", "--duration-s", "20", "--runs", "2", "--rates-hz", "1", "0.5",
               "--out", str(tmp_path / "sw"), "--rrd", str(tmp_path / "sw.rrd"), "--quiet"])
    assert rc == 2 and "--rrd" in capsys.readouterr().err
    assert not (tmp_path / "sw").exists()


def test_dataset_inspect_rrd(tmp_path, verify_rrd):
    ds, rrd = tmp_path / "ds", tmp_path / "ds.rrd"
    assert main(["generate", "--num-images", "3", "--shard-size", "2", "--resolution", "128", "--seed", "4",
                 "--out", str(ds), "--quiet"]) == 0
    assert main(["dataset", "inspect", str(ds), "--count", "3", "--rrd", str(rrd)]) == 0
    from envisat_pose.datagen.dataset import iter_samples, sample_png

    samples = list(iter_samples(str(ds)))
    verify_rrd(rrd)
    static, temporal = read_rrd(rrd)
    image = temporal["/world/chaser/camera/image"]
    assert image["frame"] == [0, 1, 2]
    for i, (key, label, members) in enumerate(samples):
        assert bytes(image["EncodedImage:blob"][i][0]) == sample_png(members, label)
        m = np.array(label["in_frame"])
        np.testing.assert_allclose(temporal["/world/chaser/camera/image/keypoints_true"]["Points2D:positions"][i],
                                   np.array(label["corners_px"])[m] + 0.5, rtol=1e-6)
        depth = temporal["/world/chaser/camera/image/depth"]["EncodedDepthImage:blob"][i][0]
        assert bytes(depth) == members["depth.png"]
        K = temporal["/world/chaser/camera"]["Pinhole:image_from_camera"][i][0]
        assert K[0] == pytest.approx(label["K"][0][0])
    mask = temporal["/world/chaser/camera/image/mask"]
    assert len(mask["frame"]) == 3
    check_names = static["/world"]["AnnotationContext:context"][0][0]["class_description"]["keypoint_annotations"]
    assert [k["label"] for k in check_names] == list(CORNER_NAMES)


@pytest.mark.parametrize("verb", [
    ["simulate", "--duration-s", "10"],
    ["estimate", "--scenario", "default", "--duration-s", "10"],
    ["montecarlo", "--scenario", "default", "--duration-s", "10", "--runs", "2"],
])
def test_bad_rrd_path_fails_before_work(tmp_path, capsys, verb):
    out = ["--out", str(tmp_path / ("x" if verb[0] == "montecarlo" else "x.npz"))]
    assert main(verb + out + ["--rrd", str(tmp_path / "x.txt"), "--quiet"]) == 2
    assert "--rrd" in capsys.readouterr().err
    assert os.listdir(tmp_path) == []
    (tmp_path / "file").write_text("x")  # a missing folder is made (issue 41); a file where one must be is refused
    assert main(verb + out + ["--rrd", str(tmp_path / "file" / "x.rrd"), "--quiet"]) == 2
    assert "--rrd" in capsys.readouterr().err
    assert os.listdir(tmp_path) == ["file"]
