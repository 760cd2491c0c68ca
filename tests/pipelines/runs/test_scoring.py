"""Scoring a tracker's runs (pipelines/runs/scoring.py): every figure sees an excursion in the middle of a run, a run
that never tracks is reported (not dropped), and the figures equal direct computations on hand-built arrays."""

import numpy as np
import pytest
from scipy.stats import chi2

from envisat_pose.pipelines.runs.scoring import NEES_TAIL, score_runs, scored_masks, settled_from, spec_score
from envisat_pose.status import ACQUIRING, COASTING, LOST, STATUSES, TRACKING

RANGE_M = 50.0
SIGMA = 1e-3  # per state component, the filter's own sigma in every P below
T = 100


def synthetic_runs(R: int = 1, seed: int = 0):
    """R runs of T frames at 1 Hz, 50 m along V-bar, a consistent estimate (errors drawn from P), acquiring for
    the first 10 frames, tracking after."""
    rng = np.random.default_rng(seed)
    t = np.arange(T, dtype=float)
    x_true = np.zeros((R, T, 12))
    x_true[..., 1] = RANGE_M
    x_true[..., 9:] = 0.01
    x_hat = x_true + rng.normal(0.0, SIGMA, (R, T, 12))
    P = np.broadcast_to(np.eye(12) * SIGMA**2, (R, T, 12, 12)).copy()
    status = np.full((R, T), TRACKING)
    status[:, :10] = ACQUIRING
    return t, x_true, x_hat, P, status


def with_excursion(x_hat: np.ndarray, status: np.ndarray, frames: slice, run: int = 0):
    """A false lock in the middle of a run: 2 m and 0.2 rad of attitude (MRP ~ tan(phi/4)) off while still
    claiming tracking (coasting on some of its frames), then back on the truth."""
    x_hat = x_hat.copy()
    status = status.copy()
    x_hat[run, frames, 0] += 2.0
    x_hat[run, frames, 6] += np.tan(0.2 / 4)
    status[run, frames.start] = COASTING
    return x_hat, status


def test_the_nees_tail_is_the_chi_square_quantile():
    assert NEES_TAIL == pytest.approx(chi2.ppf(0.999, 12))
    assert NEES_TAIL == pytest.approx(32.909, abs=1e-3)  # tables of the chi-square distribution, 12 dof


def test_an_excursion_in_the_middle_shows_in_every_figure():
    t, x_true, x_hat, P, status = synthetic_runs()
    clean = score_runs(t, x_true, x_hat, P, status)
    bad_frames = slice(50, 60)
    x_bad, st_bad = with_excursion(x_hat, status, bad_frames)
    bad = score_runs(t, x_true, x_bad, P, st_bad)

    # the clean run: no false lock, NEES near 12, nothing in the tail, SPEC score 0 (errors below its floors)
    assert clean["false_lock_s"] == 0.0 and clean["false_lock_runs"] == 0
    assert 9.0 < clean["scored"]["mean_nees"] < 15.0
    assert clean["scored"]["nees_tail_share"] <= 0.02
    assert clean["scored"]["spec_score_p95"] < 0.02  # attitude noise ~0.4 deg (4 |dp|), position below its floor
    # the excursion: 10 frames at 1 Hz claimed while wrong (one of them coasting)
    assert bad["false_lock_s"] == 10.0 and bad["false_lock_runs"] == 1
    assert bad["per_run"][0]["first_false_lock_s"] == 50.0
    # every scored frame counts: 90 frames from the first tracking, the 10 bad ones 10/90 of them
    assert bad["scored"]["frames"] == 90
    assert bad["scored"]["nees_tail_share"] == pytest.approx(10 / 90)
    # SPEC per bad frame: 2 m / 50 m + 0.2 rad = 0.24; p95 of 80 zeros and 10 x 0.24 is 0.24
    assert bad["scored"]["spec_score_p95"] == pytest.approx(2.0 / RANGE_M + 0.2, abs=0.01)
    assert bad["scored"]["spec_score_median"] == pytest.approx(clean["scored"]["spec_score_median"], abs=0.005)
    rmse_pos = np.sqrt(np.mean(np.linalg.norm(x_bad[0, 10:, :3] - x_true[0, 10:, :3], axis=-1) ** 2))
    assert bad["scored"]["rmse"]["position"] == pytest.approx(rmse_pos)
    assert bad["scored"]["rmse"]["position"] > 0.5  # sqrt(10/90 x 4 m^2) = 0.67 m
    assert bad["scored"]["rmse"]["attitude"] > 3.0  # sqrt(10/90) x 11.5 deg = 3.8 deg
    assert bad["scored"]["max_attitude_deg"] == pytest.approx(np.degrees(0.2), abs=1.0)
    assert bad["scored"]["mean_nees"] > 100 * clean["scored"]["mean_nees"]
    # the range bias: |rho_hat| - |rho| with rho_hat 2 m off across the line of sight (x), 50 m along it
    assert bad["scored"]["range_bias_m"] == pytest.approx(
        np.mean(np.linalg.norm(x_bad[0, 10:, :3], axis=-1) - RANGE_M))
    # the first track was correct, the run recovered and settled after the excursion
    assert bad["first_track_correct"] == 1 and bad["per_run"][0]["time_to_first_correct_track_s"] == 10.0
    assert bad["time_to_settle_s"]["median"] == 60.0
    # the PCRLB ratio sees it too (a bound equal to the filter's sigma per axis, in m and rad)
    bound = np.broadcast_to(np.array([np.sqrt(3) * SIGMA] * 4), (1, T, 4))
    r_clean = score_runs(t, x_true, x_hat, P, status, bound=bound)["scored"]["rmse_over_pcrlb"]
    r_bad = score_runs(t, x_true, x_bad, P, st_bad, bound=bound)["scored"]["rmse_over_pcrlb"]
    assert 0.8 < r_clean["position"] < 1.2
    assert r_bad["position"] > 100 and r_bad["attitude"] > 5 * r_clean["attitude"]
    assert r_bad["velocity"] == pytest.approx(r_clean["velocity"])


def test_a_wrong_first_track_is_not_a_correct_acquisition():
    t, x_true, x_hat, P, status = synthetic_runs()
    x_bad, st_bad = with_excursion(x_hat, status, slice(10, 15))
    s = score_runs(t, x_true, x_bad, P, st_bad)
    run = s["per_run"][0]
    assert run["first_tracking_s"] == 11.0  # frame 10 is coasting: declared tracking first at 11, and wrong
    assert run["first_track_correct"] is False and s["first_track_correct"] == 0
    assert run["time_to_first_correct_track_s"] == 15.0
    assert run["false_lock_s"] == 5.0  # the coasting frame counts: it claims an estimate


def test_a_run_that_never_tracks_is_reported_not_dropped():
    t, x_true, x_hat, P, status = synthetic_runs(R=2)
    status[1] = np.where(np.arange(T) % 2 == 0, ACQUIRING, LOST)
    x_hat[1] += 5.0  # whatever it holds is never claimed
    s = score_runs(t, x_true, x_hat, P, status)
    assert s["runs"] == 2 and s["runs_tracked"] == 1 and s["runs_never_tracking"] == [1]
    run = s["per_run"][1]
    assert run["tracked"] is False and run["first_tracking_s"] is None and run["first_track_correct"] is None
    assert run["time_to_first_correct_track_s"] is None and run["false_lock_s"] == 0.0
    assert s["time_to_first_correct_track_s"]["runs_without"] == 1
    assert s["frames_by_status"]["acquiring"] == 10 + 50 and s["frames_by_status"]["lost"] == 50
    assert s["scored"]["frames"] == 90  # run 0's only
    only = score_runs(t, x_true[1:], x_hat[1:], P[1:], status[1:])
    assert only["runs_tracked"] == 0 and only["scored"]["frames"] == 0
    assert only["scored"]["mean_nees"] is None and only["scored"]["rmse"]["position"] is None
    # the second half's error summary reads what est.npz holds: nothing where no frame holds an estimate (it once
    # scored the placeholder state of acquiring frames: metres and 131 deg for a run that never tracked)
    assert all(only["errors"][k][f] is None for k in ("position_m", "attitude_deg") for f in ("rms_after", "final"))
    rows = (t >= t[0] + 0.5 * (t[-1] - t[0])) & (status[0] != ACQUIRING)
    e0 = np.linalg.norm(x_hat[0][rows][:, :3] - x_true[0][rows][:, :3], axis=1)
    assert s["errors"]["position_m"]["rms_after"] == pytest.approx(float(np.sqrt(np.mean(e0 ** 2))), rel=1e-9)


def test_frames_without_a_claimed_estimate_are_counted_not_scored():
    t, x_true, x_hat, P, status = synthetic_runs()
    status[0, 40:45] = LOST
    status[0, 45:50] = ACQUIRING
    status[0, 60] = 7  # a status added later: claims nothing this package knows of
    x_hat[0, 40:50] += 100.0
    x_hat[0, 60] += 100.0
    s = score_runs(t, x_true, x_hat, P, status)
    assert s["scored"]["frames"] == 90 - 11 and s["per_run"][0]["frames_after_first_track"] == 90
    assert s["false_lock_s"] == 0.0 and s["scored"]["max_position_m"] < 0.01
    assert s["frames_by_status"]["code 7"] == 1
    mask = scored_masks(status)
    assert not mask[0, :10].any() and not mask[0, 40:50].any() and not mask[0, 60] and mask[0, 50:60].all()


def test_spec_score_floors_and_sum():
    e = {"position_m": np.array([0.1, 0.2, 1.0]), "range_true_m": np.array([50.0, 50.0, 50.0]),
         "attitude_deg": np.array([0.1, 0.2, 10.0])}
    # 0.1/50 = 0.002 < 2.173e-3 and 0.1 deg < 0.169: 0; 0.2/50 = 0.004 and 0.2 deg; 1/50 and 10 deg
    np.testing.assert_allclose(spec_score(e), [0.0, 0.004 + np.radians(0.2), 0.02 + np.radians(10.0)])


def test_settling_waits_for_a_claimed_estimate():
    t = np.arange(10.0)
    pos, att = np.full(10, 0.01), np.full(10, 0.1)
    claimed = np.isin(np.where(np.arange(10) >= 4, TRACKING, ACQUIRING), (TRACKING, COASTING))
    assert settled_from(t, pos, att) == 0.0
    assert settled_from(t, pos, att, claimed) == 4.0
    pos[6] = 0.2
    assert settled_from(t, pos, att, claimed) == 7.0
    pos[9] = 0.2
    assert settled_from(t, pos, att, claimed) is None
    assert STATUSES[TRACKING] == "tracking" and STATUSES[COASTING] == "coasting"


def test_each_run_has_its_own_figures_beside_the_pooled_ones():
    """Three runs, the second over-confident (its errors 3x its covariance's sigma): the pooled mean NEES mixes
    them; each run's own figures (over its own scored frames) show which one is out of band."""
    t, x_true, x_hat, P, status = synthetic_runs(R=3, seed=5)
    x_hat = x_hat.copy()
    x_hat[1] = x_true[1] + 3.0 * (x_hat[1] - x_true[1])
    out = score_runs(t, x_true, x_hat, P, status)
    per = [r["scored"] for r in out["per_run"]]
    assert [p["frames"] for p in per] == [90, 90, 90]
    assert 9.0 < per[0]["mean_nees"] < 15.0 and 9.0 < per[2]["mean_nees"] < 15.0
    assert 80.0 < per[1]["mean_nees"] < 135.0  # 9 x 12 expected
    assert out["scored"]["mean_nees"] == pytest.approx(np.mean([p["mean_nees"] for p in per]))


@pytest.mark.parametrize("off, lock_s", [("attitude", 10.0), ("position", 10.0), ("neither", 0.0)])
def test_either_half_of_the_correct_rule_alone_makes_a_false_lock(off, lock_s):
    """A claimed frame is correct only when both its attitude (within 5 deg) and its position (within 2 % of the
    range) are: 10 deg off about z with the position exact, or 3 % of the range off with the attitude exact, is
    a false lock; 4.9 deg and 1.9 % is not."""
    t, x_true, x_hat, P, status = synthetic_runs()
    bad = slice(50, 60)
    x_off = x_hat.copy()
    x_off[0, bad, :6] = x_true[0, bad, :6]
    x_off[0, bad, 6:9] = 0.0  # the truth's attitude is the identity (MRP 0)
    if off == "attitude":
        x_off[0, bad, 8] = np.tan(np.radians(10.0) / 4)  # 10 deg about z (MRP tan(phi / 4) along the axis)
    elif off == "position":
        x_off[0, bad, 0] += 0.03 * RANGE_M
    else:
        x_off[0, bad, 8] = np.tan(np.radians(4.9) / 4)
        x_off[0, bad, 0] += 0.019 * RANGE_M
    assert score_runs(t, x_true, x_off, P, status)["false_lock_s"] == lock_s


def test_a_twin_nothing_tells_apart_is_scored_as_the_truth():
    """With the pose defined up to a half-turn about z (a symmetric target's `equivalent`), an estimate turned by
    that half-turn plus 2 deg more about z is 2 deg off; without it, 178. The turned attitude is built here with
    scipy from the twin's definition (Gamma' = S Gamma)."""
    from scipy.spatial.transform import Rotation

    from envisat_pose.attitude import mrp_to_dcm
    from envisat_pose.pipelines.runs.scoring import frame_errors, nearest_truth

    rng = np.random.default_rng(2)
    x_true = np.zeros((5, 12))
    x_true[:, 1] = RANGE_M
    x_true[:, 6:9] = rng.normal(0.0, 0.2, (5, 3))
    S = np.diag([-1.0, -1.0, 1.0])
    x_hat = x_true.copy()
    for k in range(5):
        M = Rotation.from_rotvec([0, 0, np.radians(2.0)]).as_matrix() @ S @ mrp_to_dcm(x_true[k, 6:9])
        p = Rotation.from_matrix(M).as_mrp()
        if not np.allclose(mrp_to_dcm(p), M, atol=1e-9):  # the other convention: the transposed matrix
            p = Rotation.from_matrix(M.T).as_mrp()
        assert np.allclose(mrp_to_dcm(p), M, atol=1e-9)
        x_hat[k, 6:9] = p
    P = np.broadcast_to(np.eye(12) * SIGMA**2, (5, 12, 12))
    twin = frame_errors(nearest_truth(x_true, x_hat, S[None]), x_hat, P)["attitude_deg"]
    plain = frame_errors(nearest_truth(x_true, x_hat, None), x_hat, P)["attitude_deg"]
    assert np.allclose(twin, 2.0, atol=1e-6) and np.allclose(plain, 178.0, atol=1e-6)
