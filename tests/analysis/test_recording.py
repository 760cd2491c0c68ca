"""The Rerun logger (analysis.recording), read back with Rerun's own reader: layout, timelines, values.

Values are checked against the arrays they came from and against independent computations (scipy's quaternion
convention, the covariance rebuilt from the ellipsoid), never against the logger's own helpers.
"""

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from envisat_pose.analysis import recording, recording_layout, recording_writers
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


REFERENCE_HALF_M = np.array([5.0, 1.375, 1.0375])  # ENVISAT's main body, reference sheet, section 5
CORNERS_T = np.array([[5.0, 1.375, 1.0375], [5.0, -1.375, 1.0375], [5.0, -1.375, -1.0375], [5.0, 1.375, -1.0375],
                      [-5.0, 1.375, 1.0375], [-5.0, -1.375, 1.0375], [-5.0, -1.375, -1.0375],
                      [-5.0, 1.375, -1.0375]])  # corners A-H, reference sheet, section 5
UPPER_STAGE = "models/upper_stage.xml"
CUBESAT = "models/cubesat_3u.xml"


def packed_rgb(values) -> np.ndarray:
    """Rerun's packed RGBA (0xRRGGBBAA) -> (N, 3) ints."""
    v = np.asarray(values, dtype=np.uint64)
    return np.stack([(v >> 24) & 255, (v >> 16) & 255, (v >> 8) & 255], axis=1).astype(int)


def logged_mesh(static, entity="/world/target/model"):
    """(triangles (F, 3, 3) m, colours (F, 3, 3) ints, normals (F, 3, 3)) of a logged Mesh3D."""
    m = static[entity]
    pos = np.array(m["Mesh3D:vertex_positions"], dtype=float)
    idx = np.array(m["Mesh3D:triangle_indices"], dtype=int).reshape(-1, 3)
    rgb = packed_rgb(m["Mesh3D:vertex_colors"])
    normals = np.array(m["Mesh3D:vertex_normals"], dtype=float)
    return pos[idx], rgb[idx], normals[idx]


def envisat_materials_from_the_xml():
    """{rgb (0-255 ints): [(geom name, type), ...]} of the drawn geoms of body `target` in models/envisat.xml
    (group 4, the appendages, left out), read with ElementTree."""
    import xml.etree.ElementTree as ET

    from envisat_pose.geometry import model_path

    root = ET.parse(model_path()).getroot()
    rgba = {m.get("name"): [float(v) for v in m.get("rgba").split()] for m in root.iter("material")}
    body = next(b for b in root.iter("body") if b.get("name") == "target")
    out = {}
    for g in body.iter("geom"):
        if g.get("group") == "4":
            continue
        rgb = tuple(int(round(255 * v)) for v in rgba[g.get("material")][:3])
        out.setdefault(rgb, []).append((g.get("name"), g.get("type")))
    return out


def test_the_target_model_is_its_drawn_surface_in_its_materials(tmp_path):
    """ENVISAT's Mesh3D: each triangle one colour, its geom's material's (models/envisat.xml); 12 triangles a box,
    128 the 32-sided boom; the face plates span the main body of the reference sheet, the array x in [-22, -8]
    (centre -15, half 7), the boom x in [-8, -5]; flat-shaded (each normal the unit normal of its triangle)."""
    path = tmp_path / "truth.rrd"
    with recording_writers._Recording(str(path), recording_layout.truth_blueprint()) as rec:
        recording_layout.log_static_scene(rec)
    static, _ = read_rrd(path)
    tri, rgb, normals = logged_mesh(static)
    assert (rgb == rgb[:, :1]).all()  # one colour a triangle
    materials = envisat_materials_from_the_xml()
    # within 1 of 255 x the file's decimals (MuJoCo keeps them as float32: 0.30 x 255 = 76.5000031 rounds up)
    of_colour = {c: (np.abs(rgb[:, 0] - c) <= 1).all(axis=1) for c in materials}
    for c, geoms in materials.items():
        n_expected = sum(12 if kind == "box" else 128 for _, kind in geoms)
        assert of_colour[c].sum() == n_expected, geoms
    assert sum(of_colour.values()).max() == 1 and sum(m.sum() for m in of_colour.values()) == len(tri)
    by_geom = {name: of_colour[c] for c, geoms in materials.items() for name, _ in geoms}
    faces = by_geom["face_px"] | by_geom["face_py"] | by_geom["face_my"]  # panel, foil, foil_silver: the plates
    pts = tri[faces].reshape(-1, 3)
    np.testing.assert_allclose(pts.max(axis=0), REFERENCE_HALF_M, atol=1e-6)
    np.testing.assert_allclose(pts.min(axis=0), -REFERENCE_HALF_M, atol=1e-6)
    array = tri[by_geom["array"]].reshape(-1, 3)
    np.testing.assert_allclose([array[:, 0].min(), array[:, 0].max()], [-22.0, -8.0], atol=1e-6)
    boom = tri[by_geom["boom"]].reshape(-1, 3)
    np.testing.assert_allclose([boom[:, 0].min(), boom[:, 0].max()], [-8.0, -5.0], atol=1e-6)
    assert np.linalg.norm(boom[:, 1:], axis=1).max() == pytest.approx(0.08, abs=1e-6)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    np.testing.assert_allclose(normals, np.repeat(n[:, None], 3, axis=1), atol=1e-5)


def test_truth_recording_layout_and_values(tmp_path, short_truth):
    tr = short_truth
    path = tmp_path / "truth.rrd"
    recording.write_truth_recording(str(path), tr)
    static, temporal = read_rrd(path)
    N = len(tr.t_s)
    for entity in ("/world/target", "/world/keypoints_true", "/world/chaser/camera/image/keypoints_true",
                   "/metrics/range_m", "/metrics/visible_keypoints", "/metrics/in_frame_keypoints"):
        assert temporal[entity]["frame"] == list(range(N)), entity
        np.testing.assert_allclose(seconds(temporal[entity]["sim_time"]), tr.t_s, atol=1e-9)
    timelines = {k for t in temporal.values() for k in t if ":" not in k}
    assert timelines == {"frame", "sim_time"}  # the design's two, no log_time / log_tick
    for entity in ("/world/target/model", "/world/chaser/camera", "/world"):
        assert entity in static and entity not in temporal
    # the annotation context: keypoints named A-H, the 12 edges
    ctx = static["/world"]["AnnotationContext:context"][0][0]["class_description"]
    assert ctx["info"]["label"] == "envisat keypoints"
    assert [k["label"] for k in ctx["keypoint_annotations"]] == list(CORNER_NAMES)
    assert [k["id"] for k in ctx["keypoint_annotations"]] == list(range(8))
    assert sorted((c["keypoint0"], c["keypoint1"]) for c in ctx["keypoint_connections"]) == \
        sorted(tuple(sorted(e)) for e in EDGES)
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
    for k in (0, N // 2, N - 1):
        rebuilt = Rotation.from_quat(quat[k]).apply(CORNERS_T) + trans[k]
        np.testing.assert_allclose(rebuilt, tr.corners_C_m[k], atol=2e-4)
    # the corners at every frame are the truth's, in A-H order, coloured by visibility
    pts = temporal["/world/keypoints_true"]
    for k in (0, N // 3, N - 1):
        np.testing.assert_allclose(np.array(pts["Points3D:positions"][k]), tr.corners_C_m[k], rtol=1e-6, atol=1e-5)
        assert pts["Points3D:keypoint_ids"][k] == list(range(8))
        r, g, b = recording_layout.VISIBLE_RGB
        green = np.array(pts["Points3D:colors"][k]) == (r << 24 | g << 16 | b << 8 | 255)  # packed RGBA
        np.testing.assert_array_equal(green, tr.visible[k])
    # the image-plane corners: the in-frame ones, OpenCV px + 0.5
    img = temporal["/world/chaser/camera/image/keypoints_true"]
    for k in (0, N - 1):
        m = tr.in_frame[k]
        np.testing.assert_allclose(np.array(img["Points2D:positions"][k]).reshape(-1, 2), tr.corners_px[k][m] + 0.5,
                                   rtol=1e-6)
        assert img["Points2D:keypoint_ids"][k] == list(np.flatnonzero(m))
    np.testing.assert_array_equal([v[0] for v in temporal["/metrics/visible_keypoints"]["Scalars:scalars"]],
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
    # the estimate's copy: ENVISAT's 12 edges between the corners A-H, and the corners, in T
    strips = np.array(static["/world/target_est/model"]["LineStrips3D:strips"], dtype=float)

    def segments(pairs):  # each segment as its two end points, either way round
        return sorted(tuple(sorted(tuple(np.round(p, 5)) for p in seg)) for seg in pairs)

    assert segments(strips) == segments(CORNERS_T[[i, j]] for i, j in EDGES)
    np.testing.assert_allclose(static["/world/target_est/model/keypoints"]["Points3D:positions"], CORNERS_T,
                               atol=1e-6)
    assert "Mesh3D:vertex_positions" not in static["/world/target_est/model"]  # a wireframe, not a second solid
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
    pts = temporal["/world/chaser/camera/image/keypoints_true"]
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
        # NIS / dof shown with or without a truth (with one, in the tracker's panel)
        assert sum("$origin/nis" in v.contents or v.origin == "metrics/nis" for v in plots) == 1
        assert any(isinstance(v, rrb.Spatial2DView) for v in views) and any(isinstance(v, rrb.Spatial3DView) for v in views)
        for v in plots:
            ranges = v.properties["VisibleTimeRanges"].ranges.as_arrow_array().to_pylist()
            assert {r["timeline"] for r in ranges} == {"sim_time", "frame"}
            assert all(r["range"]["start"] is None and r["range"]["end"] is None for r in ranges), ranges
            legend = v.properties["PlotLegend"]
            assert legend.visible.as_arrow_array().to_pylist() == [False]


# ---------------------------------------------------------------- any target: its own shape and keypoints

def keypoint_context(static):
    ctx = static["/world"]["AnnotationContext:context"][0][0]["class_description"]
    names = [k["label"] for k in ctx["keypoint_annotations"]]
    edges = sorted((c["keypoint0"], c["keypoint1"]) for c in ctx["keypoint_connections"])
    return ctx["info"]["label"], names, edges


def test_a_truth_of_another_target_draws_that_target(tmp_path):
    """`envisat simulate --rrd` of the upper stage (its config's target.file): world/target/model is the upper
    stage's drawn surface (Target.mesh's triangles, to 1e-5 m), the annotation its 12 keypoints and skeleton, the
    truth's keypoints 0..11 at every frame; no trace of ENVISAT's corners."""
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.pipelines.campaigns.simulate import run_simulate
    from envisat_pose.target import load_target

    cfg = scenario_config("default", duration_s=10.0, dt_s=2.0, seed=2, target={"file": UPPER_STAGE})
    rrd = tmp_path / "upper.rrd"
    tr = run_simulate(cfg, str(tmp_path / "upper.npz"), rrd=str(rrd))["truth"]
    static, temporal = read_rrd(rrd)
    target = load_target(UPPER_STAGE)
    mesh = target.mesh()
    tri, rgb, _ = logged_mesh(static)
    assert tri.shape == (len(mesh.faces), 3, 3)
    np.testing.assert_allclose(tri, mesh.vertices_T_m[mesh.faces], atol=1e-5)
    assert len(np.unique(tri.reshape(-1, 3).round(6), axis=0)) == len(np.unique(mesh.vertices_T_m.round(6), axis=0))
    geom_rgb = {tuple(int(round(255 * v)) for v in g.rgb) for g in target.geoms}
    assert {tuple(c) for c in rgb.reshape(-1, 3)} <= geom_rgb
    label, names, edges = keypoint_context(static)
    assert label == "upper_stage keypoints" and names == list(target.keypoint_names) and len(names) == 12
    assert edges == sorted(target.skeleton) and all(0 <= i < j < 12 for i, j in edges)
    pts = temporal["/world/keypoints_true"]
    assert all(ids == list(range(12)) for ids in pts["Points3D:keypoint_ids"])
    np.testing.assert_allclose(np.array(pts["Points3D:positions"][-1]), tr.corners_C_m[-1], rtol=1e-6, atol=1e-5)


def test_samples_of_another_target_carry_its_keypoint_names_and_mask_values(tmp_path):
    """A CubeSat label (keypoint_names, keypoints_px: K = 12) is drawn with its names; the mask's classes are the
    renderer's values of its geoms (datagen.render_view.target_mask_values: 1..G in file order), named after them."""
    from envisat_pose.datagen.render_view import target_mask_values
    from envisat_pose.target import load_target

    target = load_target(CUBESAT)
    K = target.num_keypoints
    rng = np.random.default_rng(2)
    px = rng.uniform(0, 60, (K, 2))
    in_frame = np.arange(K) % 3 != 0
    label = {"keypoint_names": list(target.keypoint_names), "keypoints_px": px.tolist(), "visible": [True] * K,
             "in_frame": in_frame.tolist(), "K": [[80.0, 0, 31.5], [0, 80.0, 23.5], [0, 0, 1]],
             "R_cam_from_target": np.eye(3).tolist(), "t_cam_from_target_m": [0.0, 0.0, 10.0],
             "depth_scale_m": 0.002}
    png = cv2.imencode(".png", np.zeros((48, 64), np.uint8))[1].tobytes()
    path = tmp_path / "cubesat.rrd"
    values = target_mask_values(target)
    recording.write_samples_recording(str(path), [recording.Sample("k0", png, label, np.zeros((48, 64), np.uint8))],
                                      target, values)
    static, temporal = read_rrd(path)
    pts = temporal["/world/chaser/camera/image/keypoints_true"]
    np.testing.assert_allclose(np.array(pts["Points2D:positions"][0]), px[in_frame] + 0.5, rtol=1e-6)
    assert pts["Points2D:labels"][0] == [n for n, f in zip(target.keypoint_names, in_frame) if f]
    assert pts["Points2D:keypoint_ids"][0] == list(np.flatnonzero(in_frame))
    mask_ctx = static["/world/chaser/camera/image/mask"]["AnnotationContext:context"][0]
    labels = {c["class_description"]["info"]["id"]: c["class_description"]["info"]["label"] for c in mask_ctx}
    assert labels == {0: "background", **{i + 1: g.name for i, g in enumerate(target.geoms)}}
    _, names, edges = keypoint_context(static)
    assert names == list(target.keypoint_names) and edges == sorted(target.skeleton)
    assert logged_mesh(static)[0].shape == (len(target.mesh().faces), 3, 3)
    # a label of another target is refused, not drawn with the wrong names
    with pytest.raises(ValueError, match="not those of the target"):
        recording.write_samples_recording(str(tmp_path / "bad.rrd"), [recording.Sample("k0", png, label)],
                                          load_target(UPPER_STAGE))


def test_the_tracker_recording_projects_and_draws_its_target(tmp_path):
    """TrackRecorder(target=CubeSat): the estimate's keypoints in the image are the CubeSat's sites carried into C
    by the state (MRP -> rotation with scipy, rho + R_C_from_T X) and projected by the pinhole (u = f x / z + cu);
    world/target_est/model its skeleton, at the estimate's frame; without a truth, no world/target/model (its
    surface with a truth: tests/analysis/test_recording_track_scene.py)."""
    from envisat_pose.target import load_target

    target = load_target(CUBESAT)
    cam = load_camera()
    x = np.zeros(12)
    x[:3] = cam.pos_C_m + cam.R_K_from_C.T @ np.array([0.2, -0.1, 12.0])  # 12 m in front of the camera
    x[6:9] = [0.1, -0.2, 0.05]  # MRP
    path = tmp_path / "track.rrd"
    rec = recording.TrackRecorder(f"save:{path}", cam, with_truth=False, target=target)
    K = target.num_keypoints
    est = {"t_s": 0.0, "x_hat": x, "P": np.eye(12) * 0.01, "status": 1, "p_best": 0.9, "nis": 3.0, "nis_dof": 10,
           "corners_px": np.full((K, 2), np.nan), "visible": np.zeros(K, bool), "rejected": np.zeros(K, bool),
           "roi_px": np.full(3, np.nan)}
    rec.log_frame(0, est, None)
    rec.close()
    static, temporal = read_rrd(path)
    p = x[6:9]
    s2 = p @ p
    q_xyzw = np.r_[2 * p, 1 - s2] / (1 + s2)  # the MRP's quaternion, scalar last (scipy)
    X_C = x[:3] + Rotation.from_quat(q_xyzw).apply(target.keypoints_T_m)
    X_K = (X_C - cam.pos_C_m) @ cam.R_K_from_C.T
    uv = np.c_[cam.f_px * X_K[:, 0] / X_K[:, 2] + cam.cu_px, cam.f_px * X_K[:, 1] / X_K[:, 2] + cam.cv_px]
    got = np.array(temporal["/world/chaser/camera/image/keypoints_estimated"]["Points2D:positions"][0])
    np.testing.assert_allclose(got, uv + 0.5, rtol=1e-6, atol=1e-3)
    assert "/world/target/model" not in static  # no truth: no true surface (it stood at the chaser)
    assert len(temporal["/world/target_est/model"]["LineStrips3D:strips"][0]) == len(target.skeleton)
    assert keypoint_context(static)[1] == list(target.keypoint_names)
