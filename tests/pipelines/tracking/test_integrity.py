"""Integrity tests of the tracker (pipelines/tracking/integrity.py), each against an independent computation or a planted
failure: a fit that kept a handful of corners, a target behind the camera, a kilometre-wide covariance, an
inconsistent window of innovations."""

import dataclasses

import numpy as np
import pytest
from scipy.stats import chi2

from envisat_pose.geometry import load_camera, load_geometry
from envisat_pose.pipelines.tracking import integrity as ig
from envisat_pose.pipelines.tracking.acquisition import BatchFit
from envisat_pose.pipelines.tracking.tracker_config import AcquireConfig, IntegrityConfig
from envisat_pose.state import MRP, POS, RATE, VEL

CFG = IntegrityConfig()
MIN_KEYPOINTS = AcquireConfig().min_keypoints
CAM = load_camera()
RADIUS = ig.target_radius_m(load_geometry().corners_T_m)


def good_state(range_m=50.0):
    x = np.zeros(12)
    x[POS] = [0.0, range_m, 0.0]  # along the default camera's boresight (+y of C)
    x[MRP] = [0.1, -0.2, 0.05]
    x[RATE] = np.radians([0.0, 2.7, 0.0])
    # 1 cm, 1 mm/s, 0.2 deg (an MRP sigma of 0.2 deg / 4 rad), 1e-5 rad/s
    P = np.diag([0.01**2] * 3 + [1e-3**2] * 3 + [(np.radians(0.2) / 4) ** 2] * 3 + [1e-5**2] * 3)
    return x, P


def test_a_physical_state_passes_and_claims():
    x, P = good_state()
    assert ig.state_problems(x, P, CAM, RADIUS, CFG) == []
    assert ig.claim_holds(x, P, CFG)


def test_a_target_behind_the_camera_is_not_a_track():
    x, P = good_state()
    x[POS] = [0.0, -50.0, 0.0]
    assert any("not in front of the camera" in p for p in ig.state_problems(x, P, CAM, RADIUS, CFG))
    x[POS] = [0.0, 0.5 * RADIUS, 0.0]  # the camera inside the box
    assert any("not in front of the camera" in p for p in ig.state_problems(x, P, CAM, RADIUS, CFG))


def test_ranges_rates_and_widths_beyond_their_bounds_are_refused():
    x, P = good_state()
    far = x.copy()
    far[POS] = [0.0, CAM.f_px * 2 * RADIUS / CFG.min_target_px * 1.01, 0.0]  # the box under min_target_px
    assert any("range" in p for p in ig.state_problems(far, P, CAM, RADIUS, CFG))
    fast = x.copy()
    fast[RATE] = np.radians([0.0, CFG.max_rate_deg_s * 1.1, 0.0])
    assert any("tumble rate" in p for p in ig.state_problems(fast, P, CAM, RADIUS, CFG))
    moving = x.copy()
    moving[VEL] = [CFG.max_speed_m_s * 1.1, 0.0, 0.0]
    assert any("speed" in p for p in ig.state_problems(moving, P, CAM, RADIUS, CFG))
    wide = P.copy()
    wide[POS, POS] = np.eye(3) * 1700.0**2  # the 1.7 km sigma once promoted to tracking
    assert any("position sigma" in p for p in ig.state_problems(x, wide, CAM, RADIUS, CFG))
    assert not ig.claim_holds(x, wide, CFG)
    indefinite = P.copy()
    indefinite[0, 0] = -1.0
    assert any("not positive definite" in p for p in ig.state_problems(x, indefinite, CAM, RADIUS, CFG))


def test_the_claim_is_three_sigma_inside_the_tolerances():
    x, P = good_state()
    P2 = P.copy()
    sig_deg = CFG.claim_att_deg / 3.0 * 1.05  # 3 sigma just beyond the claimed attitude
    P2[MRP, MRP] = np.eye(3) * (np.radians(sig_deg) / 4.0) ** 2
    assert not ig.claim_holds(x, P2, CFG)
    P2[MRP, MRP] = np.eye(3) * (np.radians(sig_deg / 1.1) / 4.0) ** 2
    assert ig.claim_holds(x, P2, CFG)


def fit(kept_per_frame, frames, rejected, chi2_value=None):
    used = np.zeros((frames, 8), bool)
    used[:, :kept_per_frame] = True
    dof = int(2 * used.sum() - 12)
    x, P = good_state()
    return BatchFit(0.0, x, P, float(dof if chi2_value is None else chi2_value), dof, used, rejected)


def test_a_fit_that_kept_a_handful_of_corners_starts_nothing():
    assert ig.fit_problems(fit(6, 20, 12), 20, CFG, MIN_KEYPOINTS) == []  # 12 of 132: what a correct fit rejects
    bad = ig.fit_problems(fit(6, 20, 100), 20, CFG, MIN_KEYPOINTS)  # 100 of 220 measured corners rejected
    assert any("rejected 100 of 220 keypoints" in p for p in bad), bad
    few = ig.fit_problems(fit(2, 20, 0), 20, CFG, MIN_KEYPOINTS)  # 2 corners a frame: not enough named corners
    assert any("kept 2.0 keypoints a frame" in p for p in few), few


def test_a_fit_beyond_its_chi_square_bound_starts_nothing():
    f = fit(6, 20, 0)
    bound = chi2.isf(CFG.prob, f.dof)
    assert ig.fit_problems(fit(6, 20, 0, 0.99 * bound), 20, CFG, MIN_KEYPOINTS) == []
    assert any("chi-square" in p for p in ig.fit_problems(fit(6, 20, 0, 1.01 * bound), 20, CFG, MIN_KEYPOINTS))


def test_the_window_test_fires_at_its_false_alarm_rate_on_consistent_innovations():
    """Windows of chi-square NIS (consistent by construction, drawn independently of the code): the share that
    fails is the test's probability, within binomial bounds; scaled by 3 (an over-confident filter) nearly all
    fail."""

    cfg = dataclasses.replace(CFG, prob=0.05)
    rng = np.random.default_rng(11)
    H, W, dof = 4000, cfg.window, 12
    win = ig.EvidenceWindow.empty(H, W)
    for _ in range(W):
        win = win.push(rng.chisquare(dof, H), np.full(H, dof), np.full(H, 6), np.zeros(H))
    fails = np.array([bool(p) for p in ig.window_problems(win, cfg)])
    assert abs(fails.mean() - 0.05) < 4 * np.sqrt(0.05 * 0.95 / H), fails.mean()
    hot = dataclasses.replace(win, nis=3.0 * win.nis)
    assert np.mean([bool(p) for p in ig.window_problems(hot, cfg)]) > 0.99


def test_rejections_are_tested_against_the_binomial_tail_of_a_correct_track():
    """rejections_improbable is scipy's binomial tail, independently summed here; a window whose last frames had
    every corner rejected (frames of another target) fails, a window with the expected share does not."""
    from math import comb

    n = 48
    for p0 in (ig.DEFAULT_REJECT_SHARE, 0.3):
        for r in (5, 15, 24):
            tail = sum(comb(n, k) * p0**k * (1 - p0) ** (n - k) for k in range(r, n + 1))
            got = ig.rejections_improbable(r, n, p0, CFG.prob)
            assert (got is None) == (tail >= CFG.prob) and (got is None or got == pytest.approx(tail))
    W = CFG.window
    win = ig.EvidenceWindow.empty(1, W)
    for k in range(W):
        rej = 6 if k >= W - 8 else 0  # eight frames with all 6 corners rejected: the images disagree for good
        win = win.push([1.0], [2], [6], [rej])
    assert any(f"rejected 48 of the last {6 * W} keypoints" in p for p in ig.window_problems(win, CFG)[0])
    burst = ig.EvidenceWindow.empty(1, W)
    for k in range(W):
        rej = 4 if k >= W - 4 else 0  # a burst of four frames of mis-named corners: a correct track keeps going
        burst = burst.push([1.0], [2], [6], [rej])
    assert ig.window_problems(burst, CFG) == [[]]
    win = ig.EvidenceWindow.empty(1, CFG.window)
    for k in range(CFG.window):
        win = win.push([1.0], [10], [6], [1 if k % 2 else 0])  # 4 of 48: a correct track's share
    assert ig.window_problems(win, CFG) == [[]]
    ok = ig.EvidenceWindow.empty(1, CFG.window).push([1.0], [10], [6], [1])
    assert ig.window_problems(ok, CFG) == [[]]
    assert ig.EvidenceWindow.empty(3, 4).push([1, 2, 3], [2, 0, 2], [1, 0, 1], [0, 0, 0]).select([0, 2]).nis.shape \
        == (2, 4)


@pytest.mark.parametrize("prob,dof", [(1e-4, 12), (1e-3, 100)])
def test_chi2_bound_is_the_quantile(prob, dof):
    assert ig.chi2_bound(prob, dof) == pytest.approx(chi2.ppf(1 - prob, dof))


def test_correlated_windows_are_dispersed_as_the_error_model_says():
    """Errors white + AR(1) (share a, coefficient phi per frame), simulated: the variance of a window's sum of
    squares over its chi-square variance is nis_sum_dispersion's kappa, and the windows beyond nis_window_bound
    at 1 % are about 1 % (the plain chi-square bound would flag several times more)."""
    from envisat_pose.perception.errormodel import ErrorModel
    from envisat_pose.pipelines.tracking.noise import nis_sum_dispersion

    a, phi, W, comps = 0.6, 0.9, 8, 12
    em = ErrorModel(ar1_share=a, ar1_phi=phi, corr_time_s=-1.0 / np.log(phi))
    kappa = nis_sum_dispersion(em, 1.0, W)
    rng = np.random.default_rng(5)
    n = 20000
    slow = rng.standard_normal((n, comps))
    sums = np.zeros(n)
    for _ in range(W):
        slow = phi * slow + np.sqrt(1 - phi**2) * rng.standard_normal((n, comps))
        e = np.sqrt(a) * slow + np.sqrt(1 - a) * rng.standard_normal((n, comps))
        sums += np.sum(e**2, axis=-1)
    dof = W * comps
    assert sums.mean() == pytest.approx(dof, rel=0.02)
    assert sums.var() / (2 * dof) == pytest.approx(kappa, rel=0.06), (sums.var() / (2 * dof), kappa)
    tail = np.mean(sums > ig.nis_window_bound(0.01, dof, kappa))
    plain = np.mean(sums > ig.chi2_bound(0.01, dof))
    assert 0.005 < tail < 0.02 and plain > 2 * tail, (tail, plain)


def test_the_slower_correlation_is_the_one_that_lasts_longer():
    """An error model with a time fit (share 0.3, 12.8 s) and a rotation fit (share 0.31, 32 deg): at 1.6 deg/s
    (a slow tumble) the view's correlation, exp(-1.6/32) per 1 s frame, outlasts the time's, exp(-1/12.8), and
    "slower" takes it; at 5 deg/s it takes the time's. Without a rate it is the time fit."""
    from envisat_pose.perception.errormodel import ErrorModel
    from envisat_pose.pipelines.tracking.noise import ar1_at, correlation_inflation

    em = ErrorModel(ar1_share=0.3, ar1_phi=np.exp(-1 / 12.8), corr_time_s=12.8, angle_share=0.31,
                    corr_angle_rad=np.radians(32.0))
    slow, fast = np.radians(1.6), np.radians(5.0)
    assert ar1_at(em, "slower", 1.0, slow) == pytest.approx((0.31, np.exp(-1.6 / 32.0)))
    assert ar1_at(em, "slower", 1.0, fast) == pytest.approx((0.3, np.exp(-1 / 12.8)))
    assert ar1_at(em, "slower", 1.0, None) == pytest.approx((0.3, np.exp(-1 / 12.8)))
    assert ar1_at(em, "rotation", 1.0, fast) == pytest.approx((0.31, np.exp(-5.0 / 32.0)))
    # the long-memory inflation 1 + 2 a phi / (1 - phi) of the chosen fit, never below either one's
    for rate in (slow, fast):
        tau = correlation_inflation(em, "long_memory", 1.0, 1.0, rate, "slower")
        each = [1 + 2 * a * p / (1 - p) for a, p in (ar1_at(em, k, 1.0, rate) for k in ("time", "rotation"))]
        assert tau == pytest.approx(max(each))


def test_a_frames_evidence_weight_is_its_share_of_the_errors_whole_correlation():
    """bank.evidence_memory = "long": a frame's cost, read against R x tau(lambda), counts tau(lambda) / tau(1) in
    a sum over every frame. The series 1 + 2 sum_k rho_k lambda^k, summed term by term, against the closed form;
    1 for white errors and a filter that keeps everything."""
    from envisat_pose.perception.errormodel import ErrorModel
    from envisat_pose.pipelines.tracking.noise import evidence_weight

    em = ErrorModel(ar1_share=0.4, ar1_phi=0.9, corr_time_s=-1 / np.log(0.9), angle_share=0.35,
                    corr_angle_rad=np.radians(20.0))
    k = np.arange(1, 5000)
    for kind, rate, (a, phi) in [("time", None, (0.4, 0.9)),
                                 ("rotation", np.radians(2.0), (0.35, np.exp(-2.0 / 20.0)))]:
        for lam in (0.0, 0.5, 0.85, 0.99):
            want = (1 + 2 * np.sum(a * phi ** k * lam ** k)) / (1 + 2 * np.sum(a * phi ** k))
            assert evidence_weight(em, "filter_memory", lam, 1.0, rate, kind) == pytest.approx(want, rel=1e-9)
    assert evidence_weight(em, "white", 0.5, 1.0, None, "time") == 1.0
    assert evidence_weight(em, "long_memory", 0.5, 1.0, None, "time") == pytest.approx(1.0)
    assert evidence_weight(ErrorModel(), "filter_memory", 0.5, 1.0, None, "time") == 1.0  # no correlation measured


def test_a_frame_that_contradicts_every_hypothesis_is_no_evidence_between_them():
    from envisat_pose.pipelines.tracking.bank import frame_discriminates

    b12 = chi2.isf(0.01, 12)  # 26.2
    # the 30 m slow-tumble trial's frame: both twins far beyond their bound, their difference no evidence
    assert not frame_discriminates(np.array([36.2, 31.1]), np.array([12, 12]), 0.01)
    # one hypothesis explains the frame: its rival's large NIS is evidence against the rival
    assert frame_discriminates(np.array([b12 - 0.1, 60.0]), np.array([12, 12]), 0.01)
    assert not frame_discriminates(np.array([b12 + 0.1, 60.0]), np.array([12, 12]), 0.01)
    # each against its own dof: 20 is beyond the bound at 6 dof (16.8), not at 12
    assert frame_discriminates(np.array([20.0, 20.0]), np.array([6, 12]), 0.01)
    assert not frame_discriminates(np.array([20.0, 20.0]), np.array([6, 6]), 0.01)
    # a hypothesis that used no corner has no say; none used at all: nothing to discard
    assert not frame_discriminates(np.array([40.0, 0.0]), np.array([12, 0]), 0.01)
    assert frame_discriminates(np.array([0.0, 0.0]), np.array([0, 0]), 0.01)


def test_one_frames_evidence_is_bounded_against_its_best():
    """bank.frame_max_log: a hypothesis loses at most max_log nats to the frame's best (one misnamed keypoint gave
    8.4 at once); one not seen gains nothing; 0 leaves the frame's log-likelihoods as they are."""
    from envisat_pose.pipelines.tracking.bank import bounded_frame_evidence

    log_l = np.array([-2.0, -10.4, -3.5, -50.0])
    seen = np.array([True, True, True, False])
    np.testing.assert_allclose(bounded_frame_evidence(log_l, seen, 3.0), [-2.0, -5.0, -3.5, 0.0])
    np.testing.assert_allclose(bounded_frame_evidence(log_l, seen, 0.0), [-2.0, -10.4, -3.5, 0.0])
    np.testing.assert_allclose(bounded_frame_evidence(log_l, ~seen, 3.0), [0.0, 0.0, 0.0, -50.0])
    assert bounded_frame_evidence(log_l, np.zeros(4, bool), 3.0).tolist() == [0.0] * 4


def test_the_window_tests_rejections_at_the_share_each_frame_expected():
    """A window whose frames expected 30 % rejections (a detector whose calibration measured that) passes 20 of 60
    corners rejected; the same counts fail at 10 % (binomial tails 0.33 and 8e-7, prob 1e-3 here); the frames'
    shares are averaged by the corners given."""
    cfg = dataclasses.replace(CFG, prob=1e-3)
    W = 10
    for share, fails in ((0.3, False), (ig.DEFAULT_REJECT_SHARE, True)):
        win = ig.EvidenceWindow.empty(1, W)
        for k in range(W):
            win = win.push([1.0], [4], [6], [2], share)
        assert bool(ig.window_problems(win, cfg)[0]) == fails, share
    mixed = ig.EvidenceWindow.empty(2, 2).push([1, 1], [2, 2], [4, 0], [0, 0], [0.5, 0.1]).push(
        [1, 1], [2, 2], [12, 6], [0, 0], [0.1, 0.1])
    assert mixed.expected.sum(-1) / mixed.given.sum(-1) == pytest.approx([(2 + 1.2) / 16, 0.1])


def test_the_tracker_expects_the_share_its_detector_measured_unless_the_config_sets_one():
    """Tracker.reject_share: the config's expected_reject_share when set; else the detector's reject curve at the
    gate's whitened radius sqrt(gate x scale) (a curve of a Gaussian detector: exp(-r^2 / 2), tabulated); else
    DEFAULT_REJECT_SHARE. The cold start's share is the config's or the default, never the measured one."""
    from types import SimpleNamespace

    from envisat_pose.perception.keypoint_cov import REJECT_GRID
    from envisat_pose.pipelines.tracking.tracker import Tracker
    from envisat_pose.pipelines.tracking.tracker_config import TrackerConfig

    curve = {"r_sigma": REJECT_GRID.tolist(), "share": np.exp(-0.5 * REJECT_GRID ** 2).tolist()}
    default, fixed = TrackerConfig(), TrackerConfig(integrity=IntegrityConfig(expected_reject_share=0.25))
    gate, scale = 9.0, np.array([1.0, 4.0])  # radii 3 and 6 sigma
    measured = Tracker.reject_share(SimpleNamespace(cfg=default, reject_curve=curve), gate, scale)
    assert measured == pytest.approx(np.exp(-0.5 * np.array([9.0, 36.0])), abs=2e-3)
    assert Tracker.reject_share(SimpleNamespace(cfg=fixed, reject_curve=curve), gate, scale).tolist() == [0.25] * 2
    assert Tracker.reject_share(SimpleNamespace(cfg=default, reject_curve=None), gate, 2.0) \
        == pytest.approx(ig.DEFAULT_REJECT_SHARE)
    # a cold start keeps the strict share whatever the detector measured: only the config moves it
    assert Tracker.cold_start_reject_share(SimpleNamespace(cfg=default, reject_curve=curve)) == ig.DEFAULT_REJECT_SHARE
    assert Tracker.cold_start_reject_share(SimpleNamespace(cfg=fixed, reject_curve=curve)) == 0.25
    with pytest.raises(Exception, match="expected_reject_share"):
        IntegrityConfig(expected_reject_share=1.5).validate()
