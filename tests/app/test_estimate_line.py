"""The lines `envisat estimate` and `envisat montecarlo` print: estimate's mean NEES carries the same 95 % bands,
in the same words, as montecarlo's summary line (it printed a bare number with "(12 expected)"), and a count of
one run reads "1 run" (it read "1 runs")."""

import numpy as np
from scipy.stats import chi2

from envisat_pose.app.cli import main
from envisat_pose.app.estimate import summary
from envisat_pose.filtering.estimator import FilterConfig


def _arrays(R: int, T: int) -> dict:
    """R runs of T steps at rest with a small error and P = I: a finite NEES, no run diverged."""
    rng = np.random.default_rng(0)
    x_true = np.zeros((R, T, 12))
    x_true[..., 6:9] = 0.01  # a small attitude (MRP)
    x_hat = x_true + 0.01 * rng.standard_normal((R, T, 12))
    return {"t_s": np.arange(T, dtype=float), "x_true": x_true, "x_hat": x_hat,
            "P": np.broadcast_to(np.eye(12), (R, T, 12, 12)).copy(), "diverged": np.zeros(R, bool),
            "judged": np.ones(R, bool)}


def test_estimate_says_the_mean_nees_with_montecarlos_bands():
    R, T = 4, 10  # the second half: 5 steps a run
    line = summary(_arrays(R, T), FilterConfig())
    run_lo, run_hi = chi2.ppf([0.025, 0.975], 12 * R) / R
    lo, hi = chi2.ppf([0.025, 0.975], 12 * R * 5) / (R * 5)
    assert (f"(95 % band {run_lo:.2f}..{run_hi:.2f} with one sample a run; {lo:.2f}..{hi:.2f} if every step were "
            "independent)") in line, line
    assert "mean NEES 0.00 (95 % band" in line, line


def test_one_run_is_said_in_the_singular(tmp_path, capsys):
    assert main(["estimate", "--scenario", "default", "--duration-s", "10", "--runs", "1", "--quiet",
                 "--out", str(tmp_path / "est.npz")]) == 0
    out = capsys.readouterr().out
    assert "(1 run x 11 steps)" in out and "1 runs" not in out, out
    assert main(["montecarlo", "--scenario", "default", "--duration-s", "10", "--runs", "1", "--quiet",
                 "--out", str(tmp_path / "mc")]) == 0
    out = capsys.readouterr().out
    assert ": 1 run x 11 steps" in out and "1 runs" not in out, out
