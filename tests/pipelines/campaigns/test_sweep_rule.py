"""The rate sweep's converged rule counts the runs that diverged against the truth, not the NIS monitor's lone
alarms (runs it flagged whose errors stayed within the NEES rule)."""

import json
import os
import re

import numpy as np

from envisat_pose.app.montecarlo import sweep_line
from envisat_pose.io import json_safe
from envisat_pose.pipelines.campaigns.campaign import MonteCarloConfig
from envisat_pose.pipelines.campaigns.report import render_sweep, sweep_gaps
from envisat_pose.pipelines.campaigns.sweep import SweepConfig, sweep_result
from envisat_pose.state import BLOCKS


def _summary(n_diverged: int, alone: int | None) -> dict:
    s = {"n_runs": 100, "n_diverged": n_diverged, "steps": 61, "settle_s": 30.0, "nees_mean": 12.0,
         "rmse": {b: 1e-3 for b in BLOCKS}, "pcrlb_rms": {b: 1e-3 for b in BLOCKS},
         "rmse_over_pcrlb": {b: 1.0 for b in BLOCKS}}
    if alone is not None:  # None: a summary written before the lone alarms were named
        s["nis_alarm_alone_runs"] = list(range(alone))
    return s


def test_lone_nis_alarms_do_not_stop_a_rate_converging():
    cfg = MonteCarloConfig(runs=100, duration_s=60.0)
    sweep = SweepConfig(rates_hz=(2.0, 1.0, 0.5), max_diverged_share=0.05)
    # 10 flagged of 100 at each rate: 8 / 4 / (not named) of them flagged by the filter alone
    # -> 2 / 6 / 10 diverged
    r = sweep_result(cfg, sweep, [2.0, 1.0, 0.5], [_summary(10, 8), _summary(10, 4), _summary(10, None)])
    assert r["converged"] == [True, False, False] and r["lowest_converged_rate_hz"] == 2.0
    assert r["n_diverged"] == [10, 10, 10] and r["n_nis_alarm_alone"] == [8, 4, 0]
    lines = sweep_line(r).splitlines()
    assert "diverged 10/100 (8 flagged by the filter alone); converged" in lines[0]
    assert "diverged 10/100 (4 flagged by the filter alone); NOT converged" in lines[1]
    assert "diverged 10/100; NOT converged" in lines[2]
    assert all("mean NEES 12.00; diverged" in line for line in lines[:3])
    html = render_sweep({"sweep": r, "dir": "sweep", "figure": "", "config": ""})
    assert "10 / 100 (8 flagged by the filter alone)" in html and "diverged against the truth" in html
    older = {k: v for k, v in r.items() if k != "n_nis_alarm_alone"}  # a sweep.json written before
    assert "flagged diverged" in render_sweep({"sweep": older, "dir": "sweep", "figure": "", "config": ""})
    assert np.isclose(r["diverged_share"][0], 0.10)


def test_a_sweeps_n_a_cell_says_why_and_the_page_names_the_field_the_rate_and_its_campaign():
    """A rate whose campaign's summary held no finite NEES nor velocity ratio (NaN, written as null in sweep.json):
    the table's cells read 'n/a (null)', not a bare n/a, and the page lists each with the rate and that rate's
    campaign file, as the campaign table's notes do; a rate with every number gets none."""
    cfg = MonteCarloConfig(runs=100, duration_s=60.0)
    sweep = SweepConfig(rates_hz=(1.0, 0.5))
    bad = _summary(0, 0)
    bad["nees_mean"], bad["rmse_over_pcrlb"]["velocity"] = float("nan"), float("nan")
    r = json.loads(json.dumps(json_safe(sweep_result(cfg, sweep, [1.0, 0.5], [_summary(0, 0), bad]))))
    c = {"sweep": r, "dir": "sw", "figure": "", "config": ""}
    cells = re.findall(r"<td>(.*?)</td>", render_sweep(c))
    assert cells.count("n/a (null)") == 2 and "n/a" not in [x for x in cells if x != "n/a (null)"]
    assert sweep_gaps(c) == [
        f"{os.path.join('sw', 'sweep.json')}: rmse_over_pcrlb.velocity at 0.5 Hz null (shown as n/a; not finite in "
        f"{os.path.join('sw', 'rate-0.5hz', 'summary.json')})",
        f"{os.path.join('sw', 'sweep.json')}: nees_mean at 0.5 Hz null (shown as n/a; not finite in "
        f"{os.path.join('sw', 'rate-0.5hz', 'summary.json')})"]
    assert "Shown as n/a:" in render_sweep(c) and "rmse_over_pcrlb.velocity at 0.5 Hz" in render_sweep(c)
    every = sweep_result(cfg, sweep, [1.0, 0.5], [_summary(0, 0)] * 2)
    whole = {**c, "sweep": json.loads(json.dumps(json_safe(every)))}
    assert sweep_gaps(whole) == [] and "Shown as n/a" not in render_sweep(whole)


def test_the_terminal_lines_say_why_a_number_is_n_a():
    """`envisat montecarlo --rates-hz`'s lines printed a bare n/a where the report says why: the sweep's value in
    memory (NaN, infinite) or read back from sweep.json (null)."""
    cfg = MonteCarloConfig(runs=100, duration_s=60.0)
    sweep = SweepConfig(rates_hz=(1.0, 0.5))
    bad = _summary(0, 0)
    bad["nees_mean"], bad["rmse_over_pcrlb"]["velocity"] = float("nan"), float("inf")
    r = sweep_result(cfg, sweep, [1.0, 0.5], [_summary(0, 0), bad])
    lines = sweep_line(r).splitlines()
    assert "n/a" not in lines[0]
    assert "velocity n/a (inf)" in lines[1] and "mean NEES n/a (nan: a run-step's NEES is not finite" in lines[1]
    read_back = json.loads(json.dumps(json_safe(r)))
    line = sweep_line(read_back).splitlines()[1]
    assert "velocity n/a (null)" in line and "mean NEES n/a (null: a run-step's NEES is not finite" in line
    assert not re.search(r"n/a(?! \()", sweep_line(r) + sweep_line(read_back))  # never a bare n/a


def test_a_rates_rmse_that_is_not_finite_reads_n_a_with_why_in_the_terminal_lines():
    """A rate whose RMSE was not finite (a run's error overflowed) printed 'RMSE position nan cm', and read back
    from sweep.json (null) the lines were a TypeError traceback; they now say n/a, the value and what it means, as
    one campaign's line does, and the ratio beside it says it is the RMSE's doing."""
    cfg = MonteCarloConfig(runs=100, duration_s=60.0)
    bad = _summary(0, 0)
    bad["rmse"]["position"], bad["rmse_over_pcrlb"]["position"] = float("nan"), float("nan")
    r = sweep_result(cfg, SweepConfig(rates_hz=(1.0, 0.5)), [1.0, 0.5], [_summary(0, 0), bad])
    for read in (r, json.loads(json.dumps(json_safe(r)))):
        line = sweep_line(read).splitlines()[1]
        stored = "nan" if read is r else "null"
        assert f"RMSE position n/a ({stored}: a run's error is not finite), attitude 0.0573 deg" in line, line
        assert f"RMSE/PCRLB position n/a ({stored}" in line, line
        assert read is not r or "RMSE/PCRLB position n/a (nan: the RMSE is not finite (nan))" in line, line
        assert "nan cm" not in line and line.endswith("NOT converged")
