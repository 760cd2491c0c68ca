"""A Monte Carlo campaign's outputs (pipelines/campaigns/campaign.py): its blocks merged in run-index order, the PCRLB
along the truth, campaign.npz, summary.json, the figures and the Rerun recording."""

from __future__ import annotations

import json
import os

import numpy as np

from envisat_pose.analysis.pcrlb import block_bounds, efficiency, pcrlb_along_truth
from envisat_pose.analysis.stats import CampaignSums, SumsFolder, campaign_summary, finalize
from envisat_pose.config import to_dict
from envisat_pose.contracts import TruthTrajectory
from envisat_pose.filtering.dynamics import propagate, trajectory_step_s
from envisat_pose.filtering.estimator import make_setup, unjudged_runs
from envisat_pose.filtering.measurements import measure, measured_probability, outage_mask
from envisat_pose.geometry import load_camera
from envisat_pose.io import atomic_write_text, json_safe, open_npz, save_npz
from envisat_pose.pipelines.campaigns.campaign_block import (
    ALONE_KEY,
    CampaignTruth,
    block_name,
    filter_run_history,
    load_campaign_truth,
    settled_mask,
)
from envisat_pose.pipelines.campaigns.campaign_config import (
    MonteCarloConfig,
    campaign_target_record,
    campaign_title,
    runs_words,
)
from envisat_pose.pipelines.campaigns.observability import warn_if_never_updated
from envisat_pose.state import BLOCKS, N_STATE

FIGURES = ("envelopes.png", "block_norms.png", "nees_nis.png", "rmse_vs_pcrlb.png")
RUN_KEYS = ("rms_block", "final_block", "max_block", "inside_share", "nees_mean", "nis_per_dof", "diverged")


def load_block(path: str) -> dict:
    with open_npz(path) as z:
        return {k: z[k] for k in z.files}


def merge_blocks(cfg: MonteCarloConfig, out_dir: str):
    """Fold the block files in run-index order. Returns (CampaignSums, per-run dict, sample_err, sample_norms);
    the per-run dict holds RUN_KEYS and nis_alarm_alone (a block written before it: none counted)."""

    folder, runs, s_err, s_norm = SumsFolder(), {k: [] for k in RUN_KEYS + ("nis_alarm_alone",)}, [], []
    for b in range(cfg.n_blocks):
        d = load_block(os.path.join(out_dir, block_name(b)))
        folder.add(CampaignSums.from_arrays(d))
        for k in RUN_KEYS:
            runs[k].append(d[f"run_{k}"])
        runs["nis_alarm_alone"].append(d.get(ALONE_KEY, np.zeros(len(d["run_diverged"]), bool)))
        s_err.append(d["sample_err"])
        s_norm.append(d["sample_norms"])
    return (folder.result(), {k: np.concatenate(v) for k, v in runs.items()}, np.concatenate(s_err),
            np.concatenate(s_norm))


def campaign_pcrlb(cfg: MonteCarloConfig, tr: CampaignTruth) -> np.ndarray:
    """PCRLB per block (T, 4) along the truth, with the corners the truth lets the filter measure at each step
    (visible, in frame for pixels, outside outages), each weighted by its probability of being measured: of
    surviving the random failures, then of being among the first max_markers survivors (measured_probability; the
    expected information: the bound of a model whose failures are random), the
    filter's P0, the measurement noise of the config and the truth's process noise (none), the Jacobians by RK4
    sub-steps fine for the truth's fastest tumble (dynamics.trajectory_step_s). Statistics' units."""

    mcfg, camera = cfg.measurement, load_camera()
    setup = make_setup(cfg.filter, mcfg.kind, camera, target=tr.target)  # the filter's keypoints and inertia
    J_T, keypoints_T_m = setup.J_T, setup.keypoints_T_m
    dt_s = 1.0 / mcfg.rate_hz
    measured = measured_probability(tr.base & ~outage_mask(tr.t_s, mcfg.outages_s)[:, None], mcfg.failure_prob,
                                    mcfg.max_markers)

    step_s = trajectory_step_s(tr.x_true)  # sub-steps as fine as the filter's at the truth's tumble

    def fx(X):
        return propagate(X, tr.chaser[:-1, None, :], dt_s, J_T, tr.mu_m3_s2, step_s, tr.gravity_gradient)

    def hx(X):
        return measure(X, mcfg.kind, camera, keypoints_T_m)

    B = pcrlb_along_truth(fx, hx, tr.x_true, measured, mcfg.corner_cov, cfg.filter.P0, np.zeros((N_STATE, N_STATE)))
    return block_bounds(B, tr.x_true)


def finish_campaign(cfg: MonteCarloConfig, out_dir: str) -> dict:
    """Merge the blocks, compute the PCRLB, write campaign.npz, the figures and summary.json (last)."""

    sums, runs, sample_err, sample_norms = merge_blocks(cfg, out_dir)
    tr = load_campaign_truth(out_dir, cfg.measurement, cfg.target)
    stats = finalize(sums)
    bound = campaign_pcrlb(cfg, tr)
    settle = cfg.settle_time_s
    arrays = {k: np.asarray(v) for k, v in vars(stats).items()}
    arrays.update(t_s=tr.t_s, pcrlb_block=bound, sample_err=sample_err, sample_norms=sample_norms,
                  **{f"run_{k}": v for k, v in runs.items()})
    save_npz(os.path.join(out_dir, "campaign.npz"), arrays)
    summary = campaign_summary(sums, tr.t_s, settle)
    if not np.any(sums.nis_runs):  # offered: the keypoints the truth let the filter measure at some step
        warn_if_never_updated(bool(np.any(tr.base & ~outage_mask(tr.t_s, cfg.measurement.outages_s)[:, None])))
    k = settled_mask(tr.t_s, settle)
    summary.update(
        scenario=cfg.scenario, target=campaign_target_record(cfg), runs=cfg.runs, seed=cfg.seed, steps=len(tr.t_s),
        duration_s=cfg.duration_s,
        measurement=to_dict(cfg.measurement),
        pcrlb_rms={b: float(np.sqrt(np.mean(bound[k, i] ** 2))) for i, b in enumerate(BLOCKS)},
        rmse_over_pcrlb=dict(zip(BLOCKS, (float(v) for v in efficiency(stats.rmse_block, bound, tr.t_s, settle)))),
        diverged_runs=[int(i) for i in np.flatnonzero(runs["diverged"])],
        nis_alarm_alone_runs=[int(i) for i in np.flatnonzero(runs["nis_alarm_alone"])],
        # runs too short for the divergence rule: counted apart, never as not diverged (docs/design.md, Divergence)
        n_unjudged=int(np.count_nonzero(unjudged_runs(runs["diverged"], len(tr.t_s), cfg.filter))),
        divergence_settle_steps=cfg.filter.divergence_settle_steps, divergence_window=cfg.filter.divergence_window,
    )
    write_figures(cfg, out_dir, tr.t_s, stats, bound, sample_err, sample_norms)
    # summary.json last: a folder that has it is a finished campaign (report.load_campaign), its figures written
    atomic_write_text(os.path.join(out_dir, "summary.json"), json.dumps(json_safe(summary), indent=1, sort_keys=True)
                      + "\n")
    return summary


def write_figures(cfg: MonteCarloConfig, out_dir: str, t_s, stats, bound, sample_err, sample_norms) -> None:
    from envisat_pose.analysis.campaign_figures import (
        plot_block_norms,
        plot_error_envelopes,
        plot_nees_nis,
        plot_rmse_vs_bound,
    )

    title = f"{campaign_title(cfg, runs_words(cfg.runs))}, {cfg.measurement.rate_hz:g} Hz, seed {cfg.seed}"
    err = sample_err if len(sample_err) else None
    norms = sample_norms if len(sample_norms) else None
    path = os.path.join
    sample_3sigma = stats.sample_3sigma if cfg.runs > 1 else None  # one run has no sample spread (NaN)
    plot_error_envelopes(t_s, err, stats.filter_3sigma, sample_3sigma, path(out_dir, FIGURES[0]), title=title)
    plot_block_norms(t_s, norms, stats.rmse_block, stats.filter_3sigma_block, path(out_dir, FIGURES[1]), title=title)
    plot_nees_nis(t_s, stats.nees_mean, stats.nees_bounds, stats.nis_mean, stats.nis_bounds,
                  path(out_dir, FIGURES[2]), title=title)
    plot_rmse_vs_bound(t_s, stats.rmse_block, bound, path(out_dir, FIGURES[3]), title=title,
                       filter_3sigma_block=stats.filter_3sigma_block)


def write_recording(cfg: MonteCarloConfig, out_dir: str, path: str) -> None:
    """A Rerun recording at path (--rrd): the truth, run 0's estimate and 3-sigma ellipsoid (run 0 filtered
    again, keeping its means and covariances: it draws what the campaign drew), the sample runs' errors and the
    campaign's bands and mean NEES from campaign.npz."""
    from envisat_pose.analysis.recording import write_campaign_recording

    tr = load_campaign_truth(out_dir, cfg.measurement, cfg.target)
    x_hat, P = filter_run_history(tr, cfg, 0)
    with open_npz(os.path.join(out_dir, "campaign.npz")) as z:
        sample_err, filt, samp = z["sample_err"], z["filter_3sigma"], z["sample_3sigma"]
        nees_mean, nees_bounds, runs = z["nees_mean"], z["nees_bounds"], int(z["n_runs"])
    write_campaign_recording(path, tr.t_s, tr.x_true, x_hat, P, sample_err, filt, samp if cfg.runs > 1 else None,
                             truth=TruthTrajectory.load(os.path.join(out_dir, "truth.npz")), target=tr.target,
                             nees_mean=nees_mean, nees_bounds=nees_bounds, runs=runs)
