"""`envisat montecarlo`'s line of one campaign printed a figure that is not finite as a bare "nan" (or "inf"); it
says n/a and what made it so, read from the summary's other figures, as a rate sweep's n/a says why: RMSE / PCRLB
is sqrt(mean RMSE^2 / mean PCRLB^2) over the settled steps, so it is not finite when that PCRLB is 0 or not finite,
or the RMSE is not; a mean NEES that is not finite comes from a run-step's NEES. Finite figures read as before."""

import math
import re

from envisat_pose.app.montecarlo import summary_line
from envisat_pose.state import BLOCKS


def summary(**changes) -> dict:
    s = {"n_runs": 100, "n_diverged": 0, "steps": 61, "settle_s": 30.0, "nees_mean": 12.0,
         "nees_bounds": [10.56, 13.53], "nees_run_bounds": [11.7, 12.3], "rmse": {b: 1e-3 for b in BLOCKS},
         "pcrlb_rms": {b: 1e-3 for b in BLOCKS}, "rmse_over_pcrlb": {b: 1.0 for b in BLOCKS}}
    for key, value in changes.items():
        if isinstance(value, dict):
            s[key] = {**s[key], **value}
        else:
            s[key] = value
    return s


def test_finite_figures_read_as_before():
    line = summary_line(summary())
    assert line.startswith("after t = 30 s: RMSE position 0.100 cm, attitude 0.0573 deg; RMSE/PCRLB position 1.000")
    assert "mean NEES 12.00 (95 % band 11.70..12.30 with one sample a run" in line and "n/a" not in line


def test_a_figure_that_is_not_finite_says_what_made_it_so():
    nan, inf = float("nan"), float("inf")
    line = summary_line(summary(pcrlb_rms={"velocity": 0.0}, rmse_over_pcrlb={"velocity": inf}))
    assert "velocity n/a (inf: the PCRLB is 0 over the settled steps)" in line, line
    line = summary_line(summary(pcrlb_rms={"attitude": nan}, rmse_over_pcrlb={"attitude": nan}))
    assert "attitude n/a (nan: the PCRLB is not finite (nan))" in line, line
    line = summary_line(summary(rmse={"position": inf}, rmse_over_pcrlb={"position": inf}, nees_mean=nan))
    assert "RMSE position n/a (inf: a run's error is not finite)" in line, line
    assert "RMSE/PCRLB position n/a (inf: the RMSE is not finite (inf))" in line, line
    assert "mean NEES n/a (nan: a run-step's NEES is not finite (a covariance singular" in line, line
    read_back = summary(rmse_over_pcrlb={"angular_velocity": None}, nees_mean=None)  # summary.json's null
    line = summary_line(read_back)
    assert "angular_velocity n/a (null)" in line and "mean NEES n/a (null:" in line, line
    bare = summary_line(summary(rmse_over_pcrlb={"velocity": math.inf}))  # no figure says why: the value
    assert "velocity n/a (inf)" in bare and not re.search(r"(?<!\()\b(nan|inf)\b", bare), bare
