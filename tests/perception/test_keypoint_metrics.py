"""The scores of another target's keypoint detector and the fit of its pixel sigma (perception/keypoint_metrics.py,
perception/keypoint_cov.py) against hand-computed cases: every expected number below is worked out in the comments
from the inputs (or is a published constant), never read back from the code."""

import math

import cv2
import numpy as np
import pytest

from envisat_pose.perception import keypoint_cov as kc
from envisat_pose.perception import keypoint_metrics as km


def two_frames():
    """2 frames of 3 keypoints; distances of the usable ones: f0 1, 5, 2; f1 sqrt(404) = 20.0998, 0 (f1 k2 is not
    usable: its 50 px is not scored)."""
    true = np.array([[[10, 10], [30, 10], [50, 50]], [[10, 10], [30, 10], [50, 50]]], float)
    pred = np.array([[[11, 10], [33, 14], [50, 52]], [[30, 12], [30, 10], [80, 90]]], float)
    usable = np.array([[True, True, True], [True, True, False]])
    called = np.array([[True, True, False], [True, True, True]])
    return pred, true, usable, called


def test_scores_over_all_and_per_keypoint():
    pred, true, usable, called = two_frames()
    s = km.score_keypoints(pred, true, usable, called, ["k0", "k1", "k2"])
    a = s["all"]
    assert a["usable"] == 5
    assert a["pck_2px"] == pytest.approx(3 / 5)  # 0, 1, 2 within 2 px (inclusive)
    assert a["pck_5px"] == pytest.approx(4 / 5)  # and the 5
    assert a["median_px"] == pytest.approx(2.0)  # of 0, 1, 2, 5, 20.0998
    assert a["p95_px"] == pytest.approx(5 + 0.8 * (math.sqrt(404) - 5))  # linear: rank 0.95 x 4 = 3.8
    # called 5, usable 5, both 4 (f0 k0 k1, f1 k0 k1): the called unusable f1 k2 and the uncalled f0 k2 miss
    assert (a["vis_precision"], a["vis_recall"], a["called"]) == (pytest.approx(0.8), pytest.approx(0.8), 5)
    # f1 k0 sits 2 px from k1's label, 20 px from its own: named wrongly (1 of the 5 called)
    assert (a["named_wrongly"], a["named_wrongly_rate"]) == (1, pytest.approx(0.2))
    k0 = s["per_keypoint"]["k0"]
    assert (k0["usable"], k0["pck_2px"], k0["pck_5px"]) == (2, 0.5, 0.5)
    assert k0["median_px"] == pytest.approx((1 + math.sqrt(404)) / 2)
    assert k0["p95_px"] == pytest.approx(1 + 0.95 * (math.sqrt(404) - 1))
    assert (k0["vis_precision"], k0["vis_recall"], k0["named_wrongly"], k0["named_wrongly_rate"]) == (1, 1, 1, 0.5)
    k2 = s["per_keypoint"]["k2"]
    assert (k2["usable"], k2["pck_2px"], k2["median_px"], k2["called"]) == (1, 1.0, 2.0, 1)
    # called once where not usable; usable once, not called
    assert (k2["vis_precision"], k2["vis_recall"]) == (0.0, 0.0)
    k1 = s["per_keypoint"]["k1"]
    assert (k1["pck_2px"], k1["pck_5px"], k1["named_wrongly"]) == (0.5, 1.0, 0)  # 5 and 0 px


def test_nothing_usable_gives_nan_not_zero():
    s = km.keypoint_scores(np.zeros((1, 2, 2)), np.ones((1, 2, 2)), np.zeros((1, 2), bool), np.zeros((1, 2), bool))
    assert s["usable"] == 0 and math.isnan(s["pck_2px"]) and math.isnan(s["median_px"])
    assert math.isnan(s["vis_precision"]) and math.isnan(s["vis_recall"])


def test_named_wrongly_needs_another_usable_label_and_not_its_own():
    true = np.array([[[0, 0], [10, 0], [20, 0]]], float)
    usable = np.array([[True, True, False]])
    # k0 1 px from k1's label (10 px from its own); k1 on k2's label, which is not usable; k2 1 px from k0's label
    pred = np.array([[[10, 1], [20, 0], [1, 0]]], float)
    assert km.wrongly_named(pred, true, usable, np.ones((1, 3), bool)).tolist() == [[True, False, True]]
    assert km.wrongly_named(pred, true, usable, np.array([[False, True, True]])).tolist() == [[False, False, True]]
    # within 5 px of its own label and of another's: its own
    close = np.array([[[0, 0], [4, 0], [20, 0]]], float)
    assert not km.wrongly_named(np.array([[[2, 0], [4, 0], [20, 0]]], float), close, usable,
                                np.ones((1, 3), bool)).any()


def test_the_best_relabeling_counts_hits_first_then_the_summed_distance():
    true = np.array([[0, 0], [100, 0], [0, 100], [100, 100]], float)
    swap = np.array([1, 0, 3, 2])
    perms = np.array([[0, 1, 2, 3], swap])
    usable = np.ones((4, 4), bool)
    exact = true
    swapped = true[swap]  # channel k lies on keypoint swap[k]'s label: the twin's naming
    off10 = true + [10, 0]  # every channel 10 px off its own label (no hit), ~90-110 px off under the swap
    # as named one hit (k0 exact), the others 94-112 px off (sum 312); as swapped no hit (two 6 px off, sum 162)
    mixed = np.array([[0, 0], [0, 50], [106, 100], [6, 100]], float)
    pred = np.stack([exact, swapped, off10, mixed])
    chosen = km.best_relabeling(pred, np.broadcast_to(true, (4, 4, 2)), usable, perms)
    assert chosen.tolist() == [0, 1, 0, 0]
    # relabeled takes channel perm[k] as keypoint k
    back = km.relabeled(pred, perms, chosen)
    assert np.array_equal(back[1], true)
    a = np.array([[[0.0], [1.0], [2.0]]])
    assert km.relabeled(a, np.array([[0, 1, 2], [2, 0, 1]]), np.array([1]))[0, :, 0].tolist() == [2.0, 0.0, 1.0]


def test_correct_errors_are_usable_called_and_within_the_radius():
    pred, true, usable, called = two_frames()
    e = km.correct_errors(pred, true, usable, called)
    ok = np.isfinite(e[..., 0])
    # f0 k0 (1 px) and k1 (5 px, inclusive) are called and usable; f0 k2 is not called; f1 k0 is 20 px off
    assert ok.tolist() == [[True, True, False], [False, True, False]]
    assert e[0, 1].tolist() == [3.0, 4.0]


def rodrigues(v) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(v, float))[0]


BOX = np.array([[0.6, 0.3, -0.2], [-0.6, -0.3, -0.2], [0.6, -0.3, -0.2], [-0.6, 0.3, -0.2], [0.6, 0.3, 0.2],
                [-0.6, -0.3, 0.2], [0.4, 0.0, 0.5], [-0.4, 0.0, 0.5]])
CAMERA = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])


def project(R, t, X=BOX, K=CAMERA):
    x = (X @ R.T + t) @ K.T
    return x[:, :2] / x[:, 2:]


def test_pnp_recovers_the_pose_it_was_given_and_drops_an_outlier():
    R, t = rodrigues([0.3, -0.2, 0.5]), np.array([0.2, -0.1, 8.0])
    px = project(R, t)
    got = km.pnp_pose(px, np.ones(8, bool), CAMERA, BOX)
    assert got is not None and np.allclose(got[0], R, atol=1e-6) and np.allclose(got[1], t, atol=1e-5)
    bad = px.copy()
    bad[3] += [40.0, -30.0]  # 50 px off: RANSAC's outlier
    got = km.pnp_pose(bad, np.ones(8, bool), CAMERA, BOX)
    assert got is not None and np.allclose(got[0], R, atol=1e-5) and np.allclose(got[1], t, atol=1e-4)
    assert km.pnp_pose(px, np.array([1, 1, 1, 0, 0, 0, 0, 0], bool), CAMERA, BOX) is None  # 3 points


def test_pnp_refuses_a_pose_with_an_inlier_behind_the_camera(monkeypatch):
    """The guard after the solver: a pose that puts any inlier at depth <= 0 is no pose. The refinement is made
    to return the identity attitude at t = (0, 0, tz): the box's keypoints then lie at depths z + tz for its z of
    -0.2, 0.2 and 0.5 m, so tz 0.2 puts four at depth exactly 0 (refused), tz 0.25 all in front (kept)."""
    R, t = rodrigues([0.3, -0.2, 0.5]), np.array([0.2, -0.1, 8.0])
    px = project(R, t)
    real = cv2.solvePnP
    for tz, kept in ((0.2, False), (0.25, True), (-8.0, False)):
        def fake(*args, _tz=tz, **kw):  # the solver's own answer, replaced by the planted pose
            real(*args, **kw)
            return True, np.zeros((3, 1)), np.array([[0.0], [0.0], [_tz]])
        monkeypatch.setattr(km.cv2, "solvePnP", fake)
        got = km.pnp_pose(px, np.ones(8, bool), CAMERA, BOX)
        assert (got is not None) == kept, tz
        if kept:
            assert np.allclose(got[0], np.eye(3)) and np.allclose(got[1], [0.0, 0.0, tz])


def test_pose_error_in_degrees_and_percent_of_range():
    Rz30 = rodrigues([0, 0, math.radians(30)])
    rot, trans = km.pose_error(Rz30, [0, 0.5, 10.0], np.eye(3), [0, 0, 10.0])
    assert rot == pytest.approx(30.0) and trans == pytest.approx(5.0)  # 0.5 m of a 10 m range
    R = rodrigues([0.1, 0.2, -0.3])
    assert km.pose_error(R @ rodrigues([0, math.radians(4), 0]), [3, 4, 0], R, [0, 0, 50])[0] == pytest.approx(4.0)
    assert km.pose_error(R, [3, 4, 50], R, [0, 0, 50]) == pytest.approx((0.0, 10.0), abs=1e-6)  # 5 m of 50 m


def test_pose_summary_over_the_solved_frames():
    s = km.pose_summary(np.array([[1.0, 2.0], [3.0, 4.0], [np.nan, np.nan]]))
    assert s["frames"] == 3 and s["solved_share"] == pytest.approx(2 / 3)
    assert (s["rotation_deg_median"], s["translation_pct_median"]) == (2.0, 3.0)
    assert s["rotation_deg_p95"] == pytest.approx(1 + 0.95 * 2) and s["translation_pct_p95"] == pytest.approx(3.9)


def test_a_pose_far_off_is_a_pose_but_not_a_correct_one():
    # an untrained network's PnP returns poses thousands of % of the range off: each one a pose, none correct
    s = km.pose_summary(np.array([[1.0, 2.0], [4.9, 857688.0], [170.0, 1.0], [5.0, 5.0], [np.nan, np.nan]]))
    assert s["solved_share"] == pytest.approx(4 / 5)
    assert s["correct_share"] == pytest.approx(2 / 5)  # the first and the last on the bounds (inclusive)
    assert s["correct_within"] == [km.POSE_OK_DEG, km.POSE_OK_PCT] == [5.0, 5.0]
    assert km.pose_summary(np.full((2, 2), np.nan))["correct_share"] == 0.0



def test_pnp_solve_reports_its_inliers_and_their_reprojection_rms():
    R, t = rodrigues([0.3, -0.2, 0.5]), np.array([0.2, -0.1, 8.0])
    bad = project(R, t)
    bad[3] += [40.0, -30.0]  # RANSAC's outlier: 7 inliers, fitted exactly
    got = km.pnp_solve(bad, np.ones(8, bool), CAMERA, BOX)
    assert got["inliers"] == 7 and got["rms_px"] < 1e-3 and np.allclose(got["t"], t, atol=1e-4)


def solution(inliers=8, rms_px=0.5, range_m=10.0):
    return {"R": np.eye(3), "t": np.array([0.0, 0.0, range_m]), "inliers": inliers, "rms_px": rms_px}


def test_a_pose_found_is_a_consensus_that_fits_at_a_plausible_range():
    # the rule: >= 6 inliers, their RMS <= 5 px, the range within a factor 2 of the label's 10 m (bounds inclusive)
    t_true = np.array([0.0, 6.0, 8.0])  # 10 m
    assert km.FOUND_RULE == {"min_inliers": 6, "max_rms_px": 5.0, "range_factor": 2.0}
    assert km.pose_found(solution(), t_true)
    assert km.pose_found(solution(inliers=6, rms_px=5.0, range_m=20.0), t_true)
    assert km.pose_found(solution(range_m=5.0), t_true)
    assert not km.pose_found(solution(inliers=5), t_true)  # EPnP RANSAC's own sample: no point checks it
    assert not km.pose_found(solution(rms_px=5.01), t_true)
    assert not km.pose_found(solution(range_m=20.01), t_true) and not km.pose_found(solution(range_m=4.99), t_true)
    assert not km.pose_found(solution(range_m=6.2e8), t_true)  # the 61,945 %-of-range kind
    assert not km.pose_found(None, t_true) and not km.pose_found(solution(), np.full(3, np.nan))


def test_any_five_points_are_five_inliers_so_five_are_no_pose_found():
    # 5 pixels drawn at random (seed 3) anywhere in the frame: EPnP's RANSAC fits its 5-point sample and calls all
    # 5 inliers, unchecked (they lie tens of px off the refined pose); 8 such pixels give no consensus at all
    px = np.random.default_rng(3).uniform(0, 640, (8, 2))
    got = km.pnp_solve(px, np.arange(8) < 5, CAMERA, BOX)
    assert got["inliers"] == 5 and got["rms_px"] > 10 * km.PNP_REPROJ_PX
    assert not km.pose_found(got, got["t"])  # even at the range it gives itself
    assert km.pnp_solve(px, np.ones(8, bool), CAMERA, BOX) is None


def test_far_off_poses_are_solved_but_not_found_and_leave_the_medians_alone():
    # 4 frames: errors (deg, % of range) 1/2, 3/4 found; 120/61945 solved but not found; one not solved
    err = np.array([[1.0, 2.0], [3.0, 4.0], [120.0, 61945.0], [np.nan, np.nan]])
    s = km.pose_summary(err, np.array([True, True, False, False]))
    assert s["solved_share"] == pytest.approx(3 / 4) and s["found_share"] == pytest.approx(2 / 4)
    assert (s["rotation_deg_median"], s["translation_pct_median"]) == (2.0, 3.0)
    assert s["translation_pct_p95"] == pytest.approx(2 + 0.95 * 2)
    assert s["correct_share"] == pytest.approx(2 / 4) and s["found_rule"] == km.FOUND_RULE
    # a pose within the bounds but not found is not correct either
    assert km.pose_summary(np.array([[1.0, 1.0]]), np.array([False]))["correct_share"] == 0.0

# --- the pixel sigma per keypoint ---------------------------------------------------------------------------


def test_robust_sigma_is_the_median_absolute_error_over_0_6745():
    # |components| 0.5, 1, 2, 3: median 1.5; 1 / 0.67449 = 1.4826, the normal's MAD consistency constant
    assert kc.robust_sigma(np.array([[0.5, -1.0], [2.0, -3.0]])) == pytest.approx(1.5 * 1.482602218505602)
    # about zero, not about the median: a constant bias of 2 px is an error of 2 px
    assert kc.robust_sigma(np.full((5, 2), 2.0)) == pytest.approx(2.0 * 1.482602218505602)
    # Gaussian draws of sigma 1.3 (seed 0): within 2 % (the MAD's standard error here is ~0.6 %)
    e = np.random.default_rng(0).normal(0.0, 1.3, (20000, 2))
    assert kc.robust_sigma(e) == pytest.approx(1.3, rel=0.02)
    assert math.isnan(kc.robust_sigma(np.full((3, 2), np.nan)))


def test_the_sigmas_standard_error_is_the_mads():
    # the MAD's asymptotic efficiency at the normal is 36.76 %: var(sigma) = sigma^2 / (2 m 0.3676) over m values
    assert kc.MAD_VARIANCE == pytest.approx(0.5 / 0.3676, rel=1e-3)
    se = kc.sigma_standard_error(np.array([1.0]), np.array([20]))[0]
    assert se == pytest.approx(math.sqrt(1.3605 / 40), rel=1e-4)
    # and it is what robust_sigma spreads by: 4000 sets of 20 detections (seed 2) of sigma 1
    draws = np.random.default_rng(2).normal(0.0, 1.0, (4000, 20, 2))
    spread = np.std([kc.robust_sigma(d) for d in draws])
    assert spread == pytest.approx(math.sqrt(1.3605 / 40), rel=0.08)


def test_a_keypoint_with_too_few_correct_detections_is_not_calibrated():
    e = np.full((12, 2, 2), np.nan)
    e[:, 0] = [[1.0, -1.0]] * 12  # 12 detections: |components| all 1
    e[:9, 1] = [[2.0, 2.0]] * 9  # 9 < MIN_CORRECT = 10
    sigma, count = kc.fit_keypoint_sigma(e, min_count=10)
    assert count.tolist() == [12, 9] and sigma[0] == pytest.approx(1.482602218505602) and math.isnan(sigma[1])
    cov = kc.isotropic_cov(np.array([2.0, np.nan]), 3)
    assert cov.shape == (3, 2, 2, 2) and np.array_equal(cov[:, 0], np.broadcast_to(4.0 * np.eye(2), (3, 2, 2)))
    assert np.isnan(cov[:, 1]).all()


def test_nees_is_the_squared_error_over_sigma_squared_and_the_gate_is_chi2_2():
    e = np.full((4, 2, 2), np.nan)
    e[:, 0] = [[3.0, 4.0], [1.0, 1.0], [math.sqrt(5.98), 0.0], [0.0, math.sqrt(6.0)]]
    e[0, 1] = [1.0, 0.0]
    v = kc.isotropic_nees(e, np.array([5.0, np.nan]))
    assert v[:, 0] == pytest.approx([1.0, 2.0 / 25, 5.98 / 25, 6.0 / 25]) and np.isnan(v[:, 1]).all()
    # sigma 1: NEES 25, 2, 5.98, 6.0; chi-square at 2 dof has P(X > x) = exp(-x / 2): the 95 % gate is
    # -2 ln 0.05 = 5.9915, so 5.98 is within it and 6.0 and 25 are not
    c = kc.nees_check(e, np.array([1.0, np.nan]), ["p", "q"])
    assert c["all"]["count"] == 4 and c["all"]["mean_nees"] == pytest.approx((25 + 2 + 5.98 + 6.0) / 4)
    assert c["all"]["within_gate"] == pytest.approx(2 / 4)
    assert c["per_keypoint"]["q"]["count"] == 0 and math.isnan(c["per_keypoint"]["q"]["mean_nees"])


def test_the_reject_curve_is_the_whitened_errors_survival_and_counts_unusable_ones_beyond_every_radius():
    """Isotropic Gaussian errors of sigma_k: |e| / sigma_k is Rayleigh, P(> r) = exp(-r^2 / 2) (drawn here, the
    law independent of the code); a detection of a hidden keypoint is beyond every radius; one not given to the
    tracker is not counted; reject_share reads the curve at sqrt(gate x scale)."""
    rng = np.random.default_rng(5)
    sigma = np.array([0.5, 2.0, np.nan])
    err = rng.normal(size=(20_000, 3, 2)) * np.nan_to_num(sigma, nan=1.0)[None, :, None]
    usable = np.ones((20_000, 3), bool)
    usable[:2000, 0] = False  # 2000 of 40,000 given detections of a hidden keypoint
    given = np.ones((20_000, 3), bool)
    given[:, 1] = np.arange(20_000) < 18_000
    curve = kc.reject_curve(err, given, usable, sigma)
    assert curve["given"] == 38_000  # the uncalibrated keypoint is never given
    r = np.asarray(curve["r_sigma"])
    hidden = 2000 / 38_000
    want = hidden + (1 - hidden) * np.exp(-0.5 * r ** 2)
    assert np.allclose(curve["share"], want, atol=0.006)
    assert curve["share"][-1] == pytest.approx(hidden)
    assert kc.reject_share(curve, 4.0, 2.25) == pytest.approx(hidden + (1 - hidden) * np.exp(-4.5), abs=0.006)
    assert kc.reject_share(curve, 1e6) == pytest.approx(hidden)
