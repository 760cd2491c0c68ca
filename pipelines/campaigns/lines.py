"""The terminal lines of `envisat montecarlo` (app/montecarlo.py prints them): one campaign's summary line and a rate
sweep's lines. A figure that is not finite reads n/a with why: the value as stored (nan, inf, null:
report.why_not_a_number, as the report's cells) and what made it so, read from the campaign's (or the rate's) other
figures (summary_why) — RMSE / PCRLB is sqrt(mean RMSE^2 / mean PCRLB^2) over the settled steps, so it is not finite
exactly when the PCRLB over those steps is 0 (pcrlb.block_bounds clamps a block whose trace rounded below 0) or not
finite, or the RMSE is not finite; the RMSE only when a run's error is (the filter rolls a non-finite state back, so
that is an overflow); the mean NEES when a run-step's NEES is (a covariance singular to working precision, or an
error that overflowed).
"""

from __future__ import annotations

import math

from envisat_pose.pipelines.campaigns.report import unjudged_note, why_not_a_number
from envisat_pose.state import unjudged_why


def finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def summary_why(s: dict, field: str, block: str | None = None) -> str:
    """Why one campaign's summary figure (field 'rmse', 'rmse_over_pcrlb' with its block, or 'nees_mean') is not
    finite, in words (module docstring), with the value as stored (nan, inf, null)."""
    v = s[field][block] if block else s[field]
    stored = why_not_a_number(v) or str(v)
    if field == "rmse_over_pcrlb":
        bound, rmse = (s.get("pcrlb_rms") or {}).get(block), (s.get("rmse") or {}).get(block)
        if bound == 0:
            return f"{stored}: the PCRLB is 0 over the settled steps"
        if bound is not None and not finite(bound):
            return f"{stored}: the PCRLB is not finite ({why_not_a_number(bound)})"
        if rmse is not None and not finite(rmse):
            return f"{stored}: the RMSE is not finite ({why_not_a_number(rmse)})"
        return stored
    if field == "rmse":
        return f"{stored}: a run's error is not finite"
    if field == "nees_mean":
        return f"{stored}: a run-step's NEES is not finite (a covariance singular to working precision, or an " \
               "error that overflowed)"
    return stored


def _figure(s: dict, field: str, block: str | None, text) -> str:
    v = s[field][block] if block else s[field]
    return text(v) if finite(v) else f"n/a ({summary_why(s, field, block)})"


def nees_band(s: dict) -> str:
    """The mean NEES's 95 % bands: each run one sample first (a consistent campaign lies within it), then every
    run-step independent (too narrow: a run's errors are correlated in time). A summary written before the
    first: the second alone, named as such."""
    lo, hi = s["nees_bounds"]
    if "nees_run_bounds" not in s:
        return f"{lo:.2f}..{hi:.2f} if every step were independent"
    run_lo, run_hi = s["nees_run_bounds"]
    return f"{run_lo:.2f}..{run_hi:.2f} with one sample a run; {lo:.2f}..{hi:.2f} if every step were independent"


def mean_nees_words(s: dict) -> str:
    """'mean NEES 12.03 (95 % band ...)' of a summary's nees_mean with its bands (nees_band; analysis.stats.nees_bands),
    as `envisat montecarlo` and `envisat estimate` print it; not finite: n/a with why (summary_why)."""
    return "mean NEES " + _figure(s, "nees_mean", None, lambda v: f"{v:.2f}") + f" (95 % band {nees_band(s)})"


def summary_line(s: dict) -> str:
    """One line of the campaign's main numbers; a figure that is not finite as n/a with why (summary_why)."""
    ratios = ", ".join(f"{b} " + _figure(s, "rmse_over_pcrlb", b, lambda v: f"{v:.3f}") for b in s["rmse_over_pcrlb"])
    return (f"after t = {s['settle_s']:.0f} s: RMSE position "
            + _figure(s, "rmse", "position", lambda v: f"{100 * v:.3f} cm") + ", attitude "
            + _figure(s, "rmse", "attitude", lambda v: f"{math.degrees(v):.4f} deg") + f"; RMSE/PCRLB {ratios}"
            + "; " + mean_nees_words(s) + "; "
            f"diverged {s['n_diverged']}/{s['n_runs']}" + (f" ({len(s['nis_alarm_alone_runs'])} flagged by the "
                                                           "filter alone)" if s.get("nis_alarm_alone_runs") else "")
            + unjudged_note(s))


def sweep_line(r: dict) -> str:
    """One line per rate of a sweep's main numbers, and where it stops converging; a figure that is not finite as
    n/a with why, as one campaign's line says it (summary_why, over the rate's figures: rate_figures)."""
    lines, unjudged = [], r.get("n_unjudged") or [0] * len(r["rates_hz"])  # a sweep.json before it: none
    for i, rate in enumerate(r["rates_hz"]):
        s, alone = rate_figures(r, i), r["n_nis_alarm_alone"][i]
        lines.append(f"{rate:g} Hz: RMSE position " + _figure(s, "rmse", "position", lambda v: f"{100 * v:.3f} cm")
                     + ", attitude " + _figure(s, "rmse", "attitude", lambda v: f"{math.degrees(v):.4f} deg")
                     + "; RMSE/PCRLB " + ", ".join(f"{b} " + _figure(s, "rmse_over_pcrlb", b, lambda v: f"{v:.3f}")
                                                   for b in r["rmse_over_pcrlb"])
                     + "; mean NEES " + _figure(s, "nees_mean", None, lambda v: f"{v:.2f}")
                     + f"; diverged {r['n_diverged'][i]}/{r['runs']}"
                     + (f" ({alone} flagged by the filter alone)" if alone else "")
                     + (f", {unjudged[i]} not judged ({_sweep_why(r, i)})" if unjudged[i] else "") + "; "
                     + ("converged" if r["converged"][i] else "NOT converged"))
    low = r["lowest_converged_rate_hz"]
    lines.append(f"converges at every rate down to {low:g} Hz" if low is not None
                 else "does not converge at the fastest rate")
    return "\n".join(lines)


def rate_figures(r: dict, i: int) -> dict:
    """Rate i's figures of a sweep's dict (sweep.json's per-block lists) shaped as one campaign's summary:
    rmse, pcrlb_rms and rmse_over_pcrlb per block, nees_mean."""
    return {**{key: {b: v[i] for b, v in (r.get(key) or {}).items()}
               for key in ("rmse", "pcrlb_rms", "rmse_over_pcrlb")}, "nees_mean": r["nees_mean"][i]}


def _sweep_why(r: dict, i: int) -> str:  # why rate i's runs were not judged (unjudged_why)
    return unjudged_why(r["steps"][i], r["divergence_settle_steps"], r["divergence_window"])


def _run_now(n_blocks: int, timing: dict | None) -> int | None:
    """timing.json's blocks_run_now where it is a count of the campaign's N blocks, else None (no timing, a
    value of another shape)."""
    run_now = (timing or {}).get("blocks_run_now")
    if not isinstance(run_now, int) or isinstance(run_now, bool) or not 0 <= run_now <= n_blocks:
        return None
    return run_now


def resume_note(n_blocks: int, timing: dict | None) -> str:
    """'; resumed: K of N blocks kept, M run now' for a rerun that kept finished blocks (timing.json's
    blocks_run_now below the campaign's N blocks), else '' (a fresh campaign, every block redone, no timing)."""
    run_now = _run_now(n_blocks, timing)
    if run_now is None or run_now == n_blocks:
        return ""
    return f"; resumed: {n_blocks - run_now} of {n_blocks} blocks kept, {run_now} run now"


def sweep_resume_note(rates_hz: list, n_blocks: int, timings: list) -> str:
    """A rate sweep's resume_note: '; resumed: K of N blocks kept (1 Hz 2 of 2, 0.5 Hz 1 of 2), M run now' over
    its campaigns (each rate's timing.json, in the order of rates_hz; N blocks a campaign) where a rerun kept a
    finished block at some rate, else '' (a fresh sweep, or a rate's timing unreadable: nothing sure to say)."""
    run_now = [_run_now(n_blocks, t) for t in timings]
    if not run_now or None in run_now or sum(run_now) == n_blocks * len(run_now):
        return ""
    per_rate = ", ".join(f"{rate:g} Hz {n_blocks - n} of {n_blocks}" for rate, n in zip(rates_hz, run_now))
    return (f"; resumed: {n_blocks * len(run_now) - sum(run_now)} of {n_blocks * len(run_now)} blocks kept "
            f"({per_rate}), {sum(run_now)} run now")
