"""The rate sweep of `envisat montecarlo --rates-hz`: one campaign (pipelines/campaigns/campaign.py) per filter
(and measurement) rate in DIR/rate-<R>hz, each resumable like any campaign (its config as rate.config.toml, not
one `--config` reruns alone), then DIR/sweep.json (per rate: RMSE, PCRLB and RMSE/PCRLB per block, diverged share,
mean NEES, converged; the lowest rate from which every rate up converges), rate_sweep.png and
montecarlo.config.toml: the campaign's config with the sweep's [sweep] table, which `envisat montecarlo --config`
reads back to the same sweep (sweep_for)."""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass

import numpy as np

from envisat_pose.config import (
    Config,
    InputError,
    check,
    config_arg,
    load_toml,
    path_arg,
    resolve_job_config,
    to_dict,
    to_toml,
)
from envisat_pose.io import atomic_write_text, json_safe
from envisat_pose.named_scenarios import table
from envisat_pose.out_dirs import make_out_dir
from envisat_pose.out_lock import locks_output
from envisat_pose.pipelines.campaigns.campaign import (
    CONFIG_NAME,
    MonteCarloConfig,
    campaign_at_one_rate,
    campaign_job,
    check_filter_rate,
    truth_scenario,
)
from envisat_pose.pipelines.campaigns.campaign_config import campaign_target_record, campaign_title, runs_words
from envisat_pose.pools import RunnerConfig, warn_runner
from envisat_pose.provenance import source_line
from envisat_pose.resumable import manifest_path, remove_partial_files
from envisat_pose.state import BLOCKS
from envisat_pose.written_target import with_target_sha256

SWEEP_FORMAT = "envisat-pose rate sweep v1"
SWEEP_FIGURE = "rate_sweep.png"


@dataclass(frozen=True)
class SweepConfig(Config):
    """A rate sweep: one campaign per filter (and measurement) rate in rates_hz, Hz, each in its own folder.

    A rate converges when at most max_diverged_share of its runs diverged against the truth (flagged diverged, less
    those the NIS monitor flagged alone with their errors within the NEES rule: its false alarms, 1e-6 per window,
    add up over ~1e5 windows per run at 10 Hz; `truth_diverged`), every block's RMSE/PCRLB is below
    max_rmse_over_pcrlb, and the divergence rule judged its runs (a rate whose runs end before the monitors are
    armed, filter.divergence_settle_steps, is not called converged: its summary's n_unjudged)."""

    rates_hz: tuple[float, ...] = ()
    max_rmse_over_pcrlb: float = 2.0
    max_diverged_share: float = 0.05

    def validate(self, prefix: str = "sweep") -> None:
        p = f"{prefix}." if prefix else ""
        check(1 <= len(self.rates_hz) <= 32, f"{p}rates_hz", list(self.rates_hz), "1 to 32 rates in Hz")
        for i, r in enumerate(self.rates_hz):
            check(0.0 < r <= 100.0, f"{p}rates_hz[{i}]", r, "a rate in (0, 100] Hz")
        check(len(set(self.rates_hz)) == len(self.rates_hz), f"{p}rates_hz", list(self.rates_hz),
              "distinct rates")
        check(self.max_rmse_over_pcrlb > 1.0, f"{p}max_rmse_over_pcrlb", self.max_rmse_over_pcrlb,
              "a ratio above 1")
        check(0.0 <= self.max_diverged_share < 1.0, f"{p}max_diverged_share", self.max_diverged_share,
              "a share in [0, 1)")


def sweep_for(cfg: MonteCarloConfig, rates_hz=None, rate_given: bool = False,
              config_path: str | None = None) -> SweepConfig | None:
    """The rate sweep of a campaign: its scenario's [sweep] table, the [sweep] table of the config file at
    config_path (a sweep's written montecarlo.config.toml) over it, rates_hz over both (None: theirs), validated,
    every rate's step checked against the truth's before any work; None when none asks for one. rate_given: the
    caller set the campaign's single rate too (refused with a sweep: the sweep sets the rates)."""

    defaults = table(cfg.scenario, "sweep")
    written = load_toml(config_path) if config_path else {}
    in_file = written.get("sweep")
    if not defaults and in_file is None and not rates_hz:
        return None
    check(in_file is None or isinstance(in_file, dict), "sweep", in_file, "a table (rates_hz, max_rmse_over_pcrlb, "
          "max_diverged_share)")
    check(not rate_given, "measurement.rate_hz", cfg.measurement.rate_hz, "no single rate with a rate sweep (the "
          "sweep's rates_hz sets the rates)")
    file_rate = (written.get("measurement") or {}).get("rate_hz")  # a file's rate the sweep would replace unsaid
    check(file_rate is None, "measurement.rate_hz", file_rate, "no single rate beside a rate sweep: sweep.rates_hz "
          "sets each campaign's rate (remove measurement.rate_hz from the config file, or the sweep)")
    sweep = resolve_job_config(SweepConfig, {"sweep": defaults}, config_path,
                               {"sweep.rates_hz": list(rates_hz) if rates_hz else None},
                               lambda data: data["sweep"], prefix="sweep")
    for rate in sweep.rates_hz:
        sub = at_rate(cfg, rate)
        check_filter_rate(sub, truth_scenario(sub))
    return sweep


def at_rate(cfg: MonteCarloConfig, rate_hz: float) -> MonteCarloConfig:
    """The campaign of cfg with the filter and its measurements at rate_hz."""
    import dataclasses

    return dataclasses.replace(cfg, measurement=dataclasses.replace(cfg.measurement, rate_hz=float(rate_hz)))


def rate_folder(rate_hz: float) -> str:
    """The sub-folder of one rate's campaign: rate-0.05hz, rate-10hz."""
    return f"rate-{rate_hz:g}hz"


SWEEP_ENTRIES = ("sweep.json", CONFIG_NAME, SWEEP_FIGURE)


def check_sweep_folder(out_dir: str, cfg: MonteCarloConfig, sweep: SweepConfig) -> None:
    """InputError in one line unless out_dir is new, empty, or this sweep's: a campaign's folder (its manifest),
    files a sweep does not write, a rate folder of a rate not swept, a sweep.json of another scenario, runs,
    seed, duration or rates, or a rate's folder its campaign refuses (another config's campaign, files of another
    job, a stray block), all before any rate runs (once a later rate's folder was refused after the earlier rates'
    campaigns ran)."""
    if not os.path.isdir(out_dir):
        return
    if os.path.exists(manifest_path(out_dir)):
        raise InputError(f"out_dir {out_dir!r} holds a campaign, not a rate sweep: use another folder")
    rates = {rate_folder(r) for r in sweep.rates_hz}
    foreign = sorted(n for n in os.listdir(out_dir) if not n.startswith(".") and n not in SWEEP_ENTRIES
                     and n not in rates)
    if foreign:
        raise InputError(f"out_dir {out_dir!r} holds {', '.join(foreign[:3])}{', ...' if len(foreign) > 3 else ''}: "
                         "not this rate sweep's (another sweep's rates, or another job's files); use another folder")
    _check_written_sweep(out_dir, cfg, sweep)
    for rate in sorted(sweep.rates_hz):  # each rate's folder as its campaign refuses it, before any rate runs
        folder = os.path.join(out_dir, rate_folder(rate))
        if os.path.isdir(folder):
            campaign_job(at_rate(cfg, rate), folder).previous()


def _check_written_sweep(out_dir: str, cfg: MonteCarloConfig, sweep: SweepConfig) -> None:
    """InputError in one line when out_dir's sweep.json is of another scenario, runs, seed, duration or rates (an
    unreadable one is rewritten at the end)."""
    path = os.path.join(out_dir, "sweep.json")
    if not os.path.isfile(path):
        return
    try:
        with open(path, encoding="utf-8") as fh:
            was = json.load(fh)
    except (OSError, ValueError):
        return
    now = {"scenario": cfg.scenario, "runs": cfg.runs, "seed": cfg.seed, "duration_s": cfg.duration_s,
           "rates_hz": sorted(sweep.rates_hz)}
    diff = [f"{k} = {was.get(k)!r} there, {v!r} here" for k, v in now.items()
            if isinstance(was, dict) and was.get(k) != v]
    if diff:
        raise InputError(f"out_dir {out_dir!r} holds a rate sweep of another config ({'; '.join(diff[:3])}): "
                         "rerun with the same settings or use another folder")


@locks_output("out_dir", "montecarlo")
def run_sweep(cfg: MonteCarloConfig, sweep: SweepConfig, out_dir: str, runner: RunnerConfig | None = None,
              progress: bool = False) -> dict:
    """One campaign per rate in out_dir/rate-<R>hz (each resumable like any campaign), then out_dir/sweep.json
    (per rate: RMSE, PCRLB and RMSE/PCRLB per block, diverged share, mean NEES, converged) and rate_sweep.png.
    Returns sweep.json's dict."""
    from envisat_pose.analysis.campaign_figures import plot_rate_sweep

    out_dir = path_arg(out_dir, "out_dir")
    check_sweep_folder(out_dir, cfg, sweep)
    if runner is not None:
        warn_runner(config_arg(runner, RunnerConfig, "runner"), cfg.n_blocks)  # once for every rate's campaign
    make_out_dir(out_dir)
    remove_partial_files(out_dir)
    rates = sorted(sweep.rates_hz)
    summaries = []
    for rate in rates:
        if progress:
            print(f"rate sweep: {rate:g} Hz -> {os.path.join(out_dir, rate_folder(rate))}")
        summaries.append(campaign_at_one_rate(at_rate(cfg, rate), os.path.join(out_dir, rate_folder(rate)), runner,
                                             progress, in_sweep=True))
    result = sweep_result(cfg, sweep, rates, summaries)
    atomic_write_text(os.path.join(out_dir, "sweep.json"), json.dumps(json_safe(result), indent=1, sort_keys=True)
                      + "\n")
    campaign = to_dict(cfg)
    campaign["measurement"]["rate_hz"] = None  # each campaign's is the sweep's: read back, a rate beside it is refused
    written = with_target_sha256({**campaign, "sweep": to_dict(sweep)}, "montecarlo", result["target"]["sha256"])
    atomic_write_text(os.path.join(out_dir, CONFIG_NAME),
                      "# envisat montecarlo: the full validated config of this rate sweep (its [sweep] rates_hz set "
                      "each campaign's measurement.rate_hz)\n" + source_line() + to_toml(written))
    plot_rate_sweep(np.array(rates), np.array([[s["rmse"][b] for b in BLOCKS] for s in summaries]),
                    os.path.join(out_dir, SWEEP_FIGURE),
                    bound_block=np.array([[s["pcrlb_rms"][b] for b in BLOCKS] for s in summaries]),
                    diverged_share=np.array(result["diverged_share"]),
                    title=f"{campaign_title(cfg, f'{runs_words(cfg.runs)} per rate')}, {cfg.duration_s:g} s, "
                          f"seed {cfg.seed}, statistics after {summaries[0]['settle_s']:g} s")
    return result


def truth_diverged(summary: dict) -> int:
    """A campaign's runs that diverged against the truth: those flagged, less the NIS monitor's lone alarms (a
    summary written before they were named: every flagged run)."""
    return summary["n_diverged"] - len(summary.get("nis_alarm_alone_runs", ()))


def sweep_result(cfg: MonteCarloConfig, sweep: SweepConfig, rates: list, summaries: list) -> dict:
    """sweep.json: the per-rate numbers of the campaigns' summaries, and the lowest rate from which every rate
    up converges (None if the fastest does not)."""

    def per_block(key):
        return {b: [s[key][b] for s in summaries] for b in BLOCKS}

    ratio = per_block("rmse_over_pcrlb")
    converged = [truth_diverged(s) <= sweep.max_diverged_share * s["n_runs"] and not s.get("n_unjudged")
                 and all(v is not None and math.isfinite(v) and v < sweep.max_rmse_over_pcrlb
                         for v in (ratio[b][i] for b in BLOCKS))
                 for i, s in enumerate(summaries)]
    lowest = None
    for rate, ok in sorted(zip(rates, converged), reverse=True):
        if not ok:
            break
        lowest = rate
    return {"format": SWEEP_FORMAT, "scenario": cfg.scenario, "target": campaign_target_record(cfg),
            "runs": cfg.runs, "seed": cfg.seed,
            "duration_s": cfg.duration_s, "settle_s": summaries[0]["settle_s"], "rates_hz": list(rates),
            "campaigns": [rate_folder(r) for r in rates], "steps": [s["steps"] for s in summaries],
            "rmse": per_block("rmse"), "pcrlb_rms": per_block("pcrlb_rms"), "rmse_over_pcrlb": ratio,
            "n_diverged": [s["n_diverged"] for s in summaries],
            "n_nis_alarm_alone": [len(s.get("nis_alarm_alone_runs", ())) for s in summaries],
            "n_unjudged": [s.get("n_unjudged", 0) for s in summaries],
            "divergence_settle_steps": cfg.filter.divergence_settle_steps,
            "divergence_window": cfg.filter.divergence_window,
            "diverged_share": [s["n_diverged"] / s["n_runs"] for s in summaries],
            "nees_mean": [s["nees_mean"] for s in summaries], "converged": converged,
            "max_rmse_over_pcrlb": sweep.max_rmse_over_pcrlb, "max_diverged_share": sweep.max_diverged_share,
            "lowest_converged_rate_hz": lowest}
