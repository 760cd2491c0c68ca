"""Pseudo-labels (issue 40): the smoother over a tracker's segments against a closed-form RTS smoother and against
a MuJoCo truth; the labels of a pose against the corners a render shows."""

import json
import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import numpy as np
import pytest

from envisat_pose.attitude import mrp_error_angle_rad, mrp_kinematics_matrix, mrp_shadow, mrp_to_dcm, quat_to_mrp
from envisat_pose.pipelines.adaptation.pseudo_labels import (
    corner_labels,
    label_record,
    label_sigma_px,
    smooth_track,
    state_minus,
    state_plus,
    tracked_segments,
    trusted_frames,
    unscented_rts,
)
from envisat_pose.status import ACQUIRING, COASTING, LOST, TRACKING

# ---------------------------------------------------------------------------------------------------------
# segments


def test_segments_end_at_lost_and_acquiring_frames_and_open_half_turns():
    s = np.array([ACQUIRING, TRACKING, TRACKING, COASTING, TRACKING, LOST, TRACKING, TRACKING, ACQUIRING,
                  COASTING, COASTING, TRACKING, TRACKING])
    assert tracked_segments(s) == [(1, 5), (6, 8), (9, 13)]  # coasting alone (9, 10) joins the next
    n_hyp = np.array([0, 1, 1, 1, 1, 0, 1, 2, 0, 1, 1, 1, 1])
    assert tracked_segments(s, n_hyp) == [(1, 5), (6, 7), (9, 13)]
    trusted = trusted_frames(s, n_hyp)
    np.testing.assert_array_equal(np.flatnonzero(trusted), [1, 2, 4, 6, 11, 12])
    assert tracked_segments(np.array([COASTING, COASTING, ACQUIRING])) == []


# ---------------------------------------------------------------------------------------------------------
# the error state


def test_error_state_round_trips_and_matches_the_mrp_kinematics():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, 12))
    x[:, 6:9] = mrp_shadow(x[:, 6:9])
    e = rng.normal(size=(200, 12)) * 0.4
    np.testing.assert_allclose(state_minus(state_plus(x, e), x), e, atol=1e-12)
    # across the shadow set: x's MRP replaced by its shadow, the same orientation, the same error
    shadow = x.copy()
    shadow[:, 6:9] = -x[:, 6:9] / np.sum(x[:, 6:9] ** 2, axis=1, keepdims=True)
    np.testing.assert_allclose(state_minus(shadow, x)[:, 6:9], 0.0, atol=1e-12)
    # a small turn dtheta moves the MRP by B(p) dtheta (p' = B(p) w: the kinematics' sign)
    d = np.zeros_like(e)
    d[:, 6:9] = rng.normal(size=(200, 3)) * 1e-7
    dp = state_plus(x, d)[:, 6:9] - x[:, 6:9]
    np.testing.assert_allclose(dp, np.einsum("nij,nj->ni", mrp_kinematics_matrix(x[:, 6:9]), d[:, 6:9]),
                               atol=1e-12)


# ---------------------------------------------------------------------------------------------------------
# the smoother


def closed_form_rts(m, P, A, Q):
    """The textbook RTS smoother (Rauch, Tung, Striebel 1965), written out: m (T, n), P (T, n, n)."""
    ms, Ps = m.copy(), P.copy()
    for k in range(len(m) - 2, -1, -1):
        P_pred = A @ P[k] @ A.T + Q
        G = P[k] @ A.T @ np.linalg.inv(P_pred)
        ms[k] = m[k] + G @ (ms[k + 1] - A @ m[k])
        Ps[k] = P[k] + G @ (Ps[k + 1] - P_pred) @ G.T
    return ms, Ps


@pytest.mark.parametrize("n", [4, 12])
def test_linear_gaussian_equals_the_closed_form_rts_smoother(n):
    rng = np.random.default_rng(n)
    T = 80
    A = np.eye(n) + 0.1 * rng.normal(size=(n, n))
    A *= 0.98 / np.abs(np.linalg.eigvals(A)).max()  # stable: the covariances stay well conditioned
    Q = np.diag(rng.uniform(0.01, 0.1, n))
    H = rng.normal(size=(3, n))
    R = 0.5 * np.eye(3)
    # a Kalman filter's posteriors, closed form
    m, P = np.zeros(n), 4.0 * np.eye(n)
    x = rng.normal(size=n)
    ms, Ps = [], []
    for k in range(T):
        if k:
            x = A @ x + rng.multivariate_normal(np.zeros(n), Q)
            m, P = A @ m, A @ P @ A.T + Q
        S = H @ P @ H.T + R
        K = P @ H.T @ np.linalg.inv(S)
        m = m + K @ (H @ x + rng.normal(size=3) * np.sqrt(0.5) - H @ m)
        P = (np.eye(n) - K @ H) @ P
        P = 0.5 * (P + P.T)
        ms.append(m)
        Ps.append(P)
    ms, Ps = np.array(ms), np.array(Ps)
    ref_m, ref_P = closed_form_rts(ms, Ps, A, Q)
    got_m, got_P, _ = unscented_rts(ms, Ps, lambda k, X: X @ A.T, np.broadcast_to(Q, (T - 1, n, n)))
    scale = max(np.abs(ref_m).max(), 1.0)
    assert np.abs(got_m - ref_m).max() < 1e-9 * scale
    assert np.abs(got_P - ref_P).max() < 1e-9 * max(np.abs(ref_P).max(), 1.0)
    assert np.abs(got_m - ms).max() > 1e-2  # the smoother did move the estimates


@pytest.fixture(scope="module")
def filtered_runs(truth_600, chaser_of):
    """The project's UKF on noisy pixels of the MuJoCo truth of the default scenario (4 runs): posteriors to
    smooth. q_sigma: the tracker's (its filter raised to the detector's process noise)."""
    from envisat_pose.filtering.estimator import FilterConfig, run_filter
    from envisat_pose.filtering.montecarlo import MeasurementConfig, inputs_from_truth

    tr = truth_600
    cfg = FilterConfig(kernel="reference", q_sigma=(1e-7, 3e-6, 1e-5, 3e-6))
    inp = inputs_from_truth(tr, MeasurementConfig(kind="pixels", sigma_px=1.0), cfg.P0, seed=3, n_runs=4)
    res = run_filter(inp.x0_hat, cfg.P0, tr.t_s, chaser_of(tr), inp.z, inp.mask, inp.R_c, "pixels", cfg)
    status = np.full(len(tr.t_s), TRACKING)
    status[:60] = ACQUIRING  # the cold start
    status[200:205] = COASTING
    status[320] = LOST
    return tr, chaser_of(tr), cfg, res, status


def test_smoothing_a_tumbling_truth_beats_the_filter(filtered_runs):
    from envisat_pose.filtering.estimator import nees

    tr, chaser, cfg, res, status = filtered_runs
    rms = lambda a: float(np.sqrt(np.mean(np.square(a))))  # noqa: E731
    err = {"pos": [[], []], "att": [[], []], "rate": [[], []]}
    nees_s = []
    for r in range(res.x_hat.shape[0]):
        sm = smooth_track(tr.t_s, res.x_hat[r], res.P[r], status, chaser, cfg.q_sigma)
        assert sm.segments == [(60, 320), (321, 601)]
        m = sm.trusted
        assert m.sum() == 601 - 60 - 5 - 1
        for i, x in enumerate((res.x_hat[r], sm.x)):
            err["pos"][i].append(np.linalg.norm(x[m, :3] - tr.x[m, :3], axis=-1))
            err["att"][i].append(np.degrees(mrp_error_angle_rad(x[m, 6:9], tr.x[m, 6:9])))
            err["rate"][i].append(np.degrees(np.linalg.norm(x[m, 9:] - tr.x[m, 9:], axis=-1)))
        assert (np.sum(sm.x[m, 6:9] ** 2, axis=1) <= 1.0 + 1e-12).all()  # the smoothed MRP on |p| <= 1
        nees_s.append(nees(tr.x[None, m], sm.x[None, m], sm.P[None, m])[0])
        # the smoothed covariance is no wider than the filtered one
        assert (np.trace(sm.P[m], axis1=1, axis2=2) <= np.trace(res.P[r, m], axis1=1, axis2=2) * (1 + 1e-9)).all()
    # the truth's attitude crosses the shadow set (|p| = 1) inside the segments: the smoother went through it
    p = tr.x[60:, 6:9]
    assert np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1) > 1.0) >= 2
    for block, (f, s) in err.items():
        f, s = rms(np.concatenate(f)), rms(np.concatenate(s))
        print(f"{block}: filtered RMS {f:.4g}, smoothed {s:.4g} ({s / f:.2f}x)")
        assert s < 0.8 * f, block
    mean_nees = float(np.mean(np.concatenate(nees_s)))
    print(f"smoothed mean NEES {mean_nees:.1f} (12 dof)")
    assert mean_nees < 24.0


def test_the_smoother_does_not_reach_across_a_lost_frame(filtered_runs):
    """What comes after a lost frame (here a track 5 m off) leaves the segment before it unchanged."""
    tr, chaser, cfg, res, status = filtered_runs
    base = smooth_track(tr.t_s, res.x_hat[0], res.P[0], status, chaser, cfg.q_sigma)
    x = res.x_hat[0].copy()
    x[321:, :3] += 5.0
    moved = smooth_track(tr.t_s, x, res.P[0], status, chaser, cfg.q_sigma)
    np.testing.assert_array_equal(moved.x[:321], base.x[:321])
    # without the lost frame the 5 m reach back
    joined = status.copy()
    joined[320] = TRACKING
    across = smooth_track(tr.t_s, x, res.P[0], joined, chaser, cfg.q_sigma)
    assert np.abs(across.x[300, :3] - base.x[300, :3]).max() > 0.1
    # outside the segments the filter's own estimate is kept
    np.testing.assert_array_equal(moved.x[:60], x[:60])
    assert (moved.segment[:60] == -1).all() and (moved.segment[60:320] == 0).all()


# ---------------------------------------------------------------------------------------------------------
# labels


def test_labels_are_the_truths_projection_and_decode_as_a_shard_label(truth_600):
    """At the truth's state the labels are MuJoCo's own projection of its sites and its face test."""
    from envisat_pose.geometry import load_camera, load_geometry
    from envisat_pose.perception.data import decode_label

    tr = truth_600
    cam = load_camera()
    lab = corner_labels(tr.x, cam)
    np.testing.assert_allclose(lab["corners_px"][tr.in_frame], tr.corners_px[tr.in_frame], atol=1e-6)
    np.testing.assert_array_equal(lab["in_frame"], tr.in_frame)
    np.testing.assert_array_equal(lab["visible"], tr.visible)
    rec = decode_label(json.dumps(label_record(tr.x[100], cam)).encode(), "pseudo")
    np.testing.assert_allclose(rec["corners_px"], lab["corners_px"][100], atol=1e-12)
    np.testing.assert_array_equal(rec["visible"], lab["visible"][100])
    np.testing.assert_array_equal(rec["in_frame"], lab["in_frame"][100])
    np.testing.assert_allclose(rec["K"], cam.K)
    # the pose in K reprojects onto the labels
    pts = rec["t_cam_from_target_m"] + load_geometry().corners_T_m @ rec["R_cam_from_target"].T
    uv = pts[:, :2] / pts[:, 2:] * cam.f_px + [cam.cu_px, cam.cv_px]
    np.testing.assert_allclose(uv, rec["corners_px"], atol=1e-9)


def test_label_sigma_grows_with_the_covariance(truth_600):
    from envisat_pose.geometry import load_camera

    cam = load_camera()
    x = truth_600.x[[50, 150]]
    P = np.diag(np.repeat(np.square([0.01, 1e-3, 2e-4, 1e-5]), 3))
    s1 = label_sigma_px(x, np.stack([P, P]), cam)
    s2 = label_sigma_px(x, np.stack([4 * P, 4 * P]), cam)
    assert s1.shape == (2, 8) and (s1 > 0).all()
    np.testing.assert_allclose(s2, 2 * s1, rtol=0.05)


# ---------------------------------------------------------------------------------------------------------
# labels against a render


def _silhouette_points(mask):
    """The rendered body's silhouette: mid-points between 4-neighbour pixels of which one shows the body (mask
    1-6) and the other the black sky (0; not the array or an appendage, 7-8). (P, 2) px, OpenCV convention.
    Face-to-face boundaries are not used: the face plates are 5 mm thick, so which plate's id a pixel on an edge
    between two visible faces shows is z-fighting within 5 mm (0.4 px at 25 m); the silhouette is exact."""
    body, sky = (mask >= 1) & (mask <= 6), mask == 0
    pts = []
    ys, xs = np.nonzero((body[:, :-1] & sky[:, 1:]) | (sky[:, :-1] & body[:, 1:]))
    pts.append(np.stack([xs + 0.5, ys], 1))
    ys, xs = np.nonzero((body[:-1, :] & sky[1:, :]) | (sky[:-1, :] & body[1:, :]))
    pts.append(np.stack([xs, ys + 0.5], 1))
    return np.concatenate(pts).astype(float)


def _rendered_corner(i, corners_px, visible_faces, pts, margin_px=6.0, band_px=1.5, min_len_px=100.0):
    """Corner i located on the render alone, where it is a vertex of the silhouette: a line fitted (total least
    squares) to the silhouette points along each of its two silhouette edges (box edges with one visible face),
    intersected. The label only says which points to take: those within band_px of the labelled edge and
    margin_px from its ends. None where the corner is no silhouette vertex or an edge is short, sparse, or the
    two meet at less than 45 deg."""
    from envisat_pose.geometry import EDGES, load_geometry

    g = load_geometry()
    lines = []
    for a, b in EDGES:
        if i not in (a, b):
            continue
        j = b if a == i else a
        faces = np.flatnonzero(g.face_corners[:, i] & g.face_corners[:, j])
        if visible_faces[faces].sum() != 1:  # a silhouette edge: one of its faces seen
            continue
        p0, p1 = corners_px[i], corners_px[j]
        length = np.linalg.norm(p1 - p0)
        d = (p1 - p0) / length
        t = (pts - p0) @ d
        dist = np.abs((pts - p0) @ np.array([-d[1], d[0]]))
        sel = (dist < band_px) & (t > margin_px) & (t < length - margin_px)
        if length < min_len_px or sel.sum() < 40:
            return None
        q = pts[sel]
        c = q.mean(0)
        _, _, vt = np.linalg.svd(q - c)
        lines.append((c, vt[0]))
    if len(lines) != 2 or abs(lines[0][1][0] * lines[1][1][1] - lines[0][1][1] * lines[1][1][0]) < 0.7:
        return None
    (c1, d1), (c2, d2) = lines
    s, _ = np.linalg.solve(np.stack([d1, -d2], 1), c2 - c1)  # c1 + s d1 = c2 + r d2
    return c1 + s * d1


def test_pseudo_labels_land_on_the_rendered_corners():
    """Labels made from a pose (here the truth, handed to the label maker only in this test) against the corners
    the renderer draws at that pose: the intersections of lines fitted to the rendered mask's region boundaries
    (datagen's renderer, 1024 px), within 0.1 px."""
    from envisat_pose.datagen.render import SceneRenderer
    from envisat_pose.datagen.render_view import View
    from envisat_pose.geometry import load_camera, load_geometry, visible_faces

    res = 1024
    cam = load_camera().scaled(res, res)
    renderer = SceneRenderer(res)
    rng = np.random.default_rng(40)
    errs, errs_off = [], []
    try:
        for _ in range(10):
            q = rng.standard_normal(4)
            q /= np.linalg.norm(q)
            rho = np.array([rng.uniform(-1, 1), rng.uniform(22.0, 30.0), rng.uniform(-1, 1)])
            x = np.concatenate([rho, np.zeros(3), quat_to_mrp(q), np.zeros(3)])
            out = renderer.render(View(rho, mrp_to_dcm(x[6:9]).T, rng.standard_normal(3)))
            lab = corner_labels(x, cam)
            off = corner_labels(x + np.r_[0.005, 0.0, 0.0, np.zeros(9)], cam)  # the pose 5 mm across the view
            pts = _silhouette_points(out.mask_u8)
            cam_T = mrp_to_dcm(x[6:9]) @ (cam.pos_C_m - rho)
            faces = visible_faces(cam_T, load_geometry())
            for i in np.flatnonzero(lab["visible"] & lab["in_frame"]):
                u, v = np.rint(lab["corners_px"][i]).astype(int)
                if not (8 <= u < res - 8 and 8 <= v < res - 8):
                    continue
                if (out.mask_u8[v - 8:v + 9, u - 8:u + 9] >= 7).any():  # the array or an appendage near it
                    continue
                found = _rendered_corner(i, lab["corners_px"], faces, pts)
                if found is not None:
                    errs.append(np.linalg.norm(found - lab["corners_px"][i]))
                    errs_off.append(np.linalg.norm(found - off["corners_px"][i]))
    finally:
        renderer.close()
    errs = np.array(errs)
    print(f"{len(errs)} corners: median {np.median(errs):.3f} px, max {errs.max():.3f} px")
    assert len(errs) >= 15
    assert errs.max() < 0.1
    assert np.median(errs_off) > 0.2  # the located corners tell a pose 5 mm off (~0.35 px) apart


def test_no_held_out_frame_moves_a_label(filtered_runs, tmp_path):
    """adapt's labels come from the frames before the cut alone: a tracked segment running on into the held-out
    part is smoothed only up to the cut, so what the track does there (here 5 m off) leaves every label as it
    was (the RTS pass once started from the segment's end inside the held-out part: held-out detections moved the
    labels the held-out verdict is then judged against)."""
    from envisat_pose.geometry import load_camera
    from envisat_pose.pipelines.adaptation.adapt import AdaptConfig
    from envisat_pose.pipelines.adaptation.track_labels import track_run_labels

    tr, chaser, cfg, res, status = filtered_runs
    cut, camera = 300, load_camera()
    dyn = {"mu_m3_s2": AdaptConfig().track.orbit.mu_m3_s2}
    acfg = AdaptConfig(max_label_sigma_px=1e6, max_labels=1000)

    def labels(x_hat, name):
        d = tmp_path / name
        d.mkdir()
        np.savez(d / "est.npz", t_s=tr.t_s, x_hat=x_hat[None], P=res.P[:1], status=status[None])
        np.savez(d / "det.npz", n_hypotheses=np.ones(len(tr.t_s), dtype=int))
        return track_run_labels(str(d), camera, AdaptConfig().track.orbit, cfg.q_sigma, dyn, cut, acfg)

    base = labels(res.x_hat[0], "base")
    x = res.x_hat[0].copy()
    x[cut:, :3] += 5.0  # the held-out part's track moved
    moved = labels(x, "moved")
    assert base["frames"].max() < cut and len(base["frames"]) > 200
    np.testing.assert_array_equal(moved["frames"], base["frames"])
    np.testing.assert_array_equal(moved["x"], base["x"])
