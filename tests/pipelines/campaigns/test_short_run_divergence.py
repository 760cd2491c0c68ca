"""A run too short for the divergence rule was counted "not diverged" without a word: `envisat montecarlo --runs 2
--duration-s 40 --init-error-scale 100` (41 steps; the monitors are armed at step 60) read mean NEES 1.18e6 and
"diverged 0/2". Such runs are now counted apart and the line says why; a run with steps after the settle steps but
no whole window is judged on the window it holds, shortened to the run; a rate sweep does not call a rate whose runs
were not judged converged."""

import json

import numpy as np
import pytest

from envisat_pose.app.cli import main
from envisat_pose.app.montecarlo import sweep_line
from envisat_pose.contracts import ContractError, Estimates
from envisat_pose.io import save_npz
from envisat_pose.pipelines.campaigns.campaign import MonteCarloConfig
from envisat_pose.pipelines.campaigns.report import campaign_rows, render_sweep
from envisat_pose.pipelines.campaigns.sweep import SweepConfig, sweep_result
from envisat_pose.state import BLOCKS

SHORT = ["--scenario", "default", "--runs", "2", "--duration-s", "40", "--init-error-scale", "100", "--quiet"]


def test_a_campaign_ending_before_the_settle_steps_counts_its_runs_apart(tmp_path, capsys):
    out = tmp_path / "c"
    assert main(["montecarlo", *SHORT, "--out", str(out)]) == 0
    line = capsys.readouterr().out
    s = json.loads((out / "summary.json").read_text())
    assert s["steps"] == 41 and s["nees_mean"] > 1e4  # as diverged as the user's
    assert s["n_diverged"] == 0 and s["n_unjudged"] == 2 and s["divergence_settle_steps"] == 60
    assert "diverged 0/2, 2 not judged (their 41 steps end before step 60" in line
    assert "filter.divergence_settle_steps = 60, divergence_window = 30" in line
    rows = dict(campaign_rows({"summary": s, "timing": {}, "config": ""}))
    assert rows["diverged runs"].startswith("0 / 2, 2 not judged (their 41 steps end before step 60")


def test_estimate_says_its_runs_were_not_judged(tmp_path, capsys):
    """The line says so, and est.npz too: its diverged False beside judged False (a reader of the file alone told
    these runs from converged ones by nothing); a file without judged (written before it) still loads, every run
    taken as judged; a flagged run stored as not judged is refused."""
    est = tmp_path / "est.npz"
    assert main(["estimate", *SHORT, "--out", str(est)]) == 0
    assert "diverged runs 0/2, 2 not judged (their 41 steps end before step 60" in capsys.readouterr().out
    loaded = Estimates.load(str(est))
    assert loaded.diverged.tolist() == [False, False] and loaded.judged.tolist() == [False, False]
    assert loaded.judged_runs().tolist() == [False, False]
    old = {k: v for k, v in loaded.arrays().items() if k != "judged"}
    save_npz(str(tmp_path / "old.npz"), old | {"config_json": np.array(loaded.config_json)})
    before = Estimates.load(str(tmp_path / "old.npz"))
    assert before.judged is None and before.judged_runs().tolist() == [True, True]
    save_npz(str(tmp_path / "bad.npz"), old | {"config_json": np.array(loaded.config_json),
                                               "diverged": np.array([False, True]), "judged": np.array([True, False])})
    with pytest.raises(ContractError, match="run 1 is 'diverged' but not 'judged'"):
        Estimates.load(str(tmp_path / "bad.npz"))


def test_estimate_after_its_settle_steps_stores_its_runs_judged(tmp_path):
    cfg = tmp_path / "settle.toml"
    cfg.write_text("[filter]\ndivergence_settle_steps = 10\n")
    est = tmp_path / "est.npz"
    assert main(["estimate", *SHORT, "--config", str(cfg), "--out", str(est)]) == 0
    loaded = Estimates.load(str(est))
    assert loaded.diverged.tolist() == [True, True] and loaded.judged.tolist() == [True, True]


def test_a_short_campaign_after_its_settle_steps_is_judged(tmp_path, capsys):
    """21 steps, settle 10, window 30: the 100 x P0 start is flagged in both runs, a consistent start in none."""
    cfg = tmp_path / "settle.toml"
    cfg.write_text("[filter]\ndivergence_settle_steps = 10\n")
    base = ["montecarlo", "--scenario", "default", "--runs", "2", "--duration-s", "20", "--config", str(cfg),
            "--quiet"]
    assert main([*base, "--init-error-scale", "100", "--out", str(tmp_path / "wild")]) == 0
    assert main([*base, "--out", str(tmp_path / "calm")]) == 0
    wild, calm = (json.loads((tmp_path / d / "summary.json").read_text()) for d in ("wild", "calm"))
    assert (wild["n_diverged"], wild["n_unjudged"], calm["n_diverged"], calm["n_unjudged"]) == (2, 0, 0, 0)
    assert "not judged" not in capsys.readouterr().out


def _summary(n_unjudged: int | None) -> dict:
    s = {"n_runs": 100, "n_diverged": 0, "steps": 41, "settle_s": 20.0, "nees_mean": 12.0,
         "rmse": {b: 1e-3 for b in BLOCKS}, "pcrlb_rms": {b: 1e-3 for b in BLOCKS},
         "rmse_over_pcrlb": {b: 1.0 for b in BLOCKS}, "nis_alarm_alone_runs": []}
    if n_unjudged is not None:  # None: a summary written before the field
        s["n_unjudged"] = n_unjudged
    return s


def test_a_sweep_rate_whose_runs_were_not_judged_is_not_converged():
    cfg = MonteCarloConfig(runs=100, duration_s=40.0)
    r = sweep_result(cfg, SweepConfig(rates_hz=(2.0, 1.0, 0.5)), [2.0, 1.0, 0.5],
                     [_summary(None), _summary(0), _summary(100)])
    assert r["converged"] == [True, True, False] and r["lowest_converged_rate_hz"] == 1.0
    assert r["n_unjudged"] == [0, 0, 100]
    lines = sweep_line(r).splitlines()
    assert "diverged 0/100; converged" in lines[1]
    assert "diverged 0/100, 100 not judged (their 41 steps end before step 60" in lines[2]
    assert lines[2].endswith("NOT converged")
    assert "0 / 100, 100 not judged" in render_sweep({"sweep": r, "dir": "sweep", "figure": "", "config": ""})
