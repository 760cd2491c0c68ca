"""The Rerun logger (analysis.recording), read back with Rerun's own reader: layout, timelines, values.

Values are checked against the arrays they came from and against independent computations (scipy's quaternion
convention, the covariance rebuilt from the ellipsoid), never against the logger's own helpers.
"""

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from envisat_pose.analysis import recording, recording_layout
from envisat_pose.analysis.recording import read_recording as read_rrd
from envisat_pose.contracts import Estimates
from envisat_pose.geometry import CORNER_NAMES, EDGES, load_camera


def seconds(durations):
    return np.array([d.total_seconds() for d in durations])


@pytest.fixture(scope="module")
def short_truth():
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate_truth

    return simulate_truth(scenario_config("default", duration_s=40.0, seed=3))


def test_target_parts_from_the_mjcf():
    parts = {p.name: p for p in recording_layout.target_parts()}
    assert set(parts) == {"body", "array", "boom"}
    np.testing.assert_allclose(parts["body"].half_sizes_m, [5.0, 1.375, 1.0375])  # reference sheet, section 5
    np.testing.assert_allclose(parts["array"].half_sizes_m, [7.0, 2.5, 0.02])
    np.testing.assert_allclose(parts["array"].center_T_m, [-15.0, 0.0, 0.0])
    boom = parts["boom"]
    assert boom.kind == "cylinder" and boom.length_m == pytest.approx(3.0) and boom.radius_m == pytest.approx(0.08)
    np.testing.assert_allclose(boom.center_T_m, [-6.5, 0.0, 0.0])
    axis = Rotation.from_quat(boom.quat_xyzw).apply([0.0, 0.0, 1.0])  # scipy is xyzw too
    np.testing.assert_allclose(np.abs(axis), [1.0, 0.0, 0.0], atol=1e-12)


def test_truth_recording_layout_and_values(tmp_path, short_truth):
    tr = short_truth
    path = tmp_path / "truth.rrd"
    recording.write_truth_recording(str(path), tr)
    static, temporal = read_rrd(path)
    N = len(tr.t_s)
    for entity in ("/world/target", "/world/corners_true", "/world/chaser/camera/image/corners_true",
                   "/metrics/range_m", "/metrics/visible_corners", "/metrics/in_frame_corners"):
        assert temporal[entity]["frame"] == list(range(N)), entity
        np.testing.assert_allclose(seconds(temporal[entity]["sim_time"]), tr.t_s, atol=1e-9)
    timelines = {k for t in temporal.values() for k in t if ":" not in k}
    assert timelines == {"frame", "sim_time"}  # the design's two, no log_time / log_tick
    for entity in ("/world/target/model/body", "/world/target/model/array", "/world/target/model/boom",
                   "/world/chaser/camera", "/world"):
        assert entity in static and entity not in temporal
    # the annotation context: keypoints named A-H, the 12 edges
    ctx = static["/world"]["AnnotationContext:context"][0][0]["class_description"]
    assert [k["label"] for k in ctx["keypoint_annotations"]] == list(CORNER_NAMES)
    assert [k["id"] for k in ctx["keypoint_annotations"]] == list(range(8))
    assert sorted((c["keypoint0"], c["keypoint1"]) for c in ctx["keypoint_connections"]) == sorted(EDGES)
    # the pinhole is load_camera's (principal point shifted to Rerun's pixel centres)
    cam = load_camera()
    K = np.array(static["/world/chaser/camera"]["Pinhole:image_from_camera"][0]).reshape(3, 3).T  # column-major
    np.testing.assert_allclose(K, [[cam.f_px, 0, cam.cu_px + 0.5], [0, cam.f_px, cam.cv_px + 0.5], [0, 0, 1]],
                               rtol=1e-6)
    assert static["/world/chaser/camera"]["Pinhole:resolution"][0] == [cam.width_px, cam.height_px]
    # pose: translation rho_C; the corner sites rebuilt with scipy's reading of the xyzw quaternion
    tgt = temporal["/world/target"]
    trans = np.array([v[0] for v in tgt["Transform3D:translation"]])
    quat = np.array([v[0] for v in tgt["Transform3D:quaternion"]])
    np.testing.assert_allclose(trans, tr.x[:, 0:3], rtol=1e-6, atol=1e-5)
    corners_T = np.array([[5.0, 1.375, 1.0375], [5.0, -1.375, 1.0375], [5.0, -1.375, -1.0375],
                          [5.0, 1.375, -1.0375], [-5.0, 1.375, 1.0375], [-5.0, -1.375, 1.0375],
                          [-5.0, -1.375, -1.0375], [-5.0, 1.375, -1.0375]])  # reference sheet, section 5
    for k in (0, N // 2, N - 1):
        rebuilt = Rotation.from_quat(quat[k]).apply(corners_T) + trans[k]
        np.testing.assert_allclose(rebuilt, tr.corners_C_m[k], atol=2e-4)
    # the corners at every frame are the truth's, in A-H order, coloured by visibility
    pts = temporal["/world/corners_true"]
    for k in (0, N // 3, N - 1):
        np.testing.assert_allclose(np.array(pts["Points3D:positions"][k]), tr.corners_C_m[k], rtol=1e-6, atol=1e-5)
        assert pts["Points3D:keypoint_ids"][k] == list(range(8))
        r, g, b = recording_layout.VISIBLE_RGB
        green = np.array(pts["Points3D:colors"][k]) == (r << 24 | g << 16 | b << 8 | 255)  # packed RGBA
        np.testing.assert_array_equal(green, tr.visible[k])
    # the image-plane corners: the in-frame ones, OpenCV px + 0.5
    img = temporal["/world/chaser/camera/image/corners_true"]
    for k in (0, N - 1):
        m = tr.in_frame[k]
        np.testing.assert_allclose(np.array(img["Points2D:positions"][k]).reshape(-1, 2), tr.corners_px[k][m] + 0.5,
                                   rtol=1e-6)
        assert img["Points2D:keypoint_ids"][k] == list(np.flatnonzero(m))
    np.testing.assert_array_equal([v[0] for v in temporal["/metrics/visible_corners"]["Scalars:scalars"]],
                                  tr.visible.sum(axis=1))


def synthetic_estimates(R=3, T=25, seed=0):
    rng = np.random.default_rng(seed)
    t_s = np.arange(T) * 2.0
    x_true = np.zeros((R, T, 12))
    x_true[..., 1] = 50.0
    x_true[..., 6:9] = 0.2 * np.sin(t_s[:, None] / 10 + np.arange(3))
    x_hat = x_true + 0.01 * rng.standard_normal((R, T, 12))
    A = rng.standard_normal((R, T, 12, 12))
    P = A @ np.swapaxes(A, -1, -2) * 1e-4 + 1e-6 * np.eye(12)
    return Estimates(t_s=t_s, x_true=x_true, x_hat=x_hat, P=P, n_meas=np.full((R, T), 8), nis=np.ones((R, T)),
                     nis_dof=np.full((R, T), 24), diverged=np.zeros(R, bool), config_json="{}")


def test_estimates_recording(tmp_path):
    est = synthetic_estimates()
    R, T = est.x_hat.shape[:2]
    path = tmp_path / "est.rrd"
    recording.write_estimates_recording(str(path), est)
    static, temporal = read_rrd(path)
    assert "/world/target_est/model/body" in static
    est_pose = temporal["/world/target_est"]
    assert est_pose["frame"] == list(range(T))
    np.testing.assert_allclose(np.array([v[0] for v in est_pose["Transform3D:translation"]]), est.x_hat[0, :, :3],
                               rtol=1e-6)
    # the ellipsoid, carried into C by the estimated attitude, gives back 9 x the position covariance
    ell = temporal["/world/target_est/position_3sigma"]
    q_est = np.array([v[0] for v in est_pose["Transform3D:quaternion"]])
    for k in (0, T - 1):
        half = np.array(ell["Ellipsoids3D:half_sizes"][k][0], dtype=float)
        q_ell = ell["Ellipsoids3D:quaternions"][k][0]
        R_C_from_ell = (Rotation.from_quat(q_est[k]) * Rotation.from_quat(q_ell)).as_matrix()
        np.testing.assert_allclose(R_C_from_ell @ np.diag(half**2) @ R_C_from_ell.T, 9 * est.P[0, k, :3, :3],
                                   rtol=1e-4, atol=1e-10)
    # one series per run; position and velocity errors are plain differences; bands from P's diagonal
    for i, entity in ((0, "/metrics/error/position_m/x"), (4, "/metrics/error/velocity_m_s/y")):
        series = temporal[entity]
        assert series["frame"] == list(range(T))
        assert static[entity]["SeriesLines:names"] == [f"run {r}" for r in range(R)]
        np.testing.assert_allclose(np.array(series["Scalars:scalars"]), (est.x_hat - est.x_true)[:, :, i].T, atol=1e-12)
        band = np.array(temporal[entity + "/filter_3sigma"]["Scalars:scalars"])
        np.testing.assert_allclose(band[:, 0], 3 * np.sqrt(est.P[:, :, i, i].mean(axis=0)), rtol=1e-12)
        np.testing.assert_allclose(band[:, 1], -band[:, 0])
        spread = np.array(temporal[entity + "/sample_3sigma"]["Scalars:scalars"])
        np.testing.assert_allclose(spread[:, 0], 3 * (est.x_hat - est.x_true)[:, :, i].std(axis=0, ddof=1), rtol=1e-9)
    # attitude in degrees: a small error's rotation vector is ~ 4 dp (rad) near p = 0 (checked loosely)
    att = np.array(temporal["/metrics/error/attitude_deg/z"]["Scalars:scalars"])
    assert att.shape == (T, R) and np.isfinite(att).all() and np.abs(att).max() < 10


def test_samples_recording(tmp_path):
    rng = np.random.default_rng(1)
    img = rng.integers(0, 255, (48, 64), dtype=np.uint8)
    mask = np.zeros((48, 64), np.uint8)
    mask[10:20, 10:30] = 3
    depth = np.zeros((48, 64), np.uint16)
    depth[10:20, 10:30] = 25000
    png = cv2.imencode(".png", img)[1].tobytes()
    dpng = cv2.imencode(".png", depth)[1].tobytes()
    K = [[80.0, 0, 31.5], [0, 80.0, 23.5], [0, 0, 1]]
    corners = rng.uniform(0, 60, (8, 2))
    in_frame = np.array([1, 1, 1, 0, 1, 1, 0, 1], bool)
    label = {"corners_px": corners.tolist(), "visible": [True] * 4 + [False] * 4, "in_frame": in_frame.tolist(),
             "K": K, "R_cam_from_target": np.eye(3).tolist(), "t_cam_from_target_m": [0.0, 0.0, 50.0],
             "depth_scale_m": 0.002, "scene": {"t_s": 12.0}}
    samples = [recording.Sample("k0", png, label, mask, dpng), recording.Sample("k1", png, label, None, None)]
    path = tmp_path / "ds.rrd"
    recording.write_samples_recording(str(path), samples)
    static, temporal = read_rrd(path)
    image = temporal["/world/chaser/camera/image"]
    assert image["frame"] == [0, 1]
    assert bytes(image["EncodedImage:blob"][0][0]) == png  # stored compressed, as the dataset's PNG
    assert image["EncodedImage:media_type"][0] == ["image/png"]
    pts = temporal["/world/chaser/camera/image/corners_true"]
    np.testing.assert_allclose(np.array(pts["Points2D:positions"][0]), corners[in_frame] + 0.5, rtol=1e-6)
    assert pts["Points2D:labels"][0] == [n for n, f in zip(CORNER_NAMES, in_frame) if f]
    assert temporal["/world/chaser/camera/image/mask"]["frame"] == [0]
    depth_row = temporal["/world/chaser/camera/image/depth"]
    assert bytes(depth_row["EncodedDepthImage:blob"][0][0]) == dpng
    assert depth_row["EncodedDepthImage:meter"][0][0] == pytest.approx(500.0)
    np.testing.assert_allclose(seconds(image["sim_time"]), [12.0, 12.0])
    mask_ctx = static["/world/chaser/camera/image/mask"]["AnnotationContext:context"][0]
    assert [c["class_description"]["info"]["label"] for c in mask_ctx][3] == "face +y"


def test_file_is_written_atomically(tmp_path):
    """A failure while logging leaves the earlier file untouched and no temporary file behind."""
    path = tmp_path / "est.rrd"
    recording.write_estimates_recording(str(path), synthetic_estimates(R=1, T=3))
    before = path.read_bytes()
    with pytest.raises(AttributeError):
        recording.write_truth_recording(str(path), None)  # fails inside, after the file was opened
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["est.rrd"]


def test_the_tracker_recording_shows_the_whole_run_in_six_plots():
    """The tracker's blueprint: at most six plot panels, each over the whole run on both timelines (not a trailing
    window) and with its legend off the data; the camera view and the 3D view beside them."""
    import rerun.blueprint as rrb

    from envisat_pose.analysis.recording_layout import track_blueprint

    for with_truth in (True, False):
        root = track_blueprint(with_truth).root_container
        views = []

        def walk(c):
            for x in getattr(c, "contents", []):
                views.append(x) if not hasattr(x, "contents") or isinstance(x, rrb.View) else walk(x)

        walk(root)
        plots = [v for v in views if isinstance(v, rrb.TimeSeriesView)]
        assert 1 <= len(plots) <= 6
        assert any(isinstance(v, rrb.Spatial2DView) for v in views) and any(isinstance(v, rrb.Spatial3DView) for v in views)
        for v in plots:
            ranges = v.properties["VisibleTimeRanges"].ranges.as_arrow_array().to_pylist()
            assert {r["timeline"] for r in ranges} == {"sim_time", "frame"}
            assert all(r["range"]["start"] is None and r["range"]["end"] is None for r in ranges), ranges
            legend = v.properties["PlotLegend"]
            assert legend.visible.as_arrow_array().to_pylist() == [False]
