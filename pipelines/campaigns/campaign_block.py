"""One block of a Monte Carlo campaign (a task of the core runner, pipelines/campaigns/campaign.py): its runs filtered with
the pure `filter_step` in time chunks of CHUNK_STEPS and reduced to sums over the runs (analysis/stats.py), so no
covariance history is held; and one run filtered alone with its history (filter_run_history, for a recording).
Run r draws from SeedSequence(seed, spawn_key=(r,)), so a block draws exactly what the campaign draws."""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass

import numpy as np

from envisat_pose.analysis.stats import (
    CampaignSums,
    RunAccumulator,
    block_error_norms,
    component_errors,
    reduce_runs,
    settled,
)
from envisat_pose.config import from_dict
from envisat_pose.contracts import TruthTrajectory
from envisat_pose.filtering.estimator import (
    Measurement,
    chaser_states,
    diverged_against_truth,
    filter_step,
    init_state,
    make_setup,
    nis_alarms_alone,
)
from envisat_pose.filtering.montecarlo import MeasurementConfig, filter_stride, make_run_inputs, truth_measurements
from envisat_pose.filtering.ukf import chart_error
from envisat_pose.io import save_npz, sha256_file
from envisat_pose.pipelines.campaigns.campaign_config import MonteCarloConfig
from envisat_pose.pipelines.campaigns.estimate import check_truth_keypoints, truth_target, with_target_file
from envisat_pose.pipelines.tracking.onboard import onboard_physics
from envisat_pose.state import N_STATE
from envisat_pose.target import Target

CHUNK_STEPS = 200  # filter steps per reduction chunk: bounds the covariances held to R x 200 x 144 floats
ALONE_KEY = "run_nis_alarm_alone"  # a block's (R,) bool: flagged diverged by the filter alone
# (nis_alarms_alone: its NIS monitor or a failed update, the NEES rule holding)


BLOCK_GLOB = os.path.join("blocks", "block-*.npz")  # every block's name matches it (one the campaign lacks: a stray)


def block_name(b: int) -> str:
    return os.path.join("blocks", f"block-{b:04d}.npz")


@dataclass(frozen=True)
class CampaignTruth:
    """The truth on the filter's grid: t_s (T,), x_true (T, 12), chaser (T, 4), z_true (T, K, m), base (T, K)
    measurable keypoints (outages not yet removed), and the filter's model constants mu_m3_s2, gravity_gradient
    and target (the truth's Target; None: ENVISAT, the filter's default model: estimate.truth_target)."""

    t_s: np.ndarray
    x_true: np.ndarray
    chaser: np.ndarray
    z_true: np.ndarray
    base: np.ndarray
    mu_m3_s2: float
    gravity_gradient: bool
    target: Target | None = None


def load_campaign_truth(out_dir: str, mcfg: MeasurementConfig, target: str | None = None) -> CampaignTruth:
    """DIR/truth.npz sampled at the filter's rate, with its noise-free measurements. target: the campaign's target
    file as this run gives it (the campaign's identity holds its sha256: estimate.with_target_file), which a
    resume from another folder finds where the truth's recorded path is not found."""

    path = os.path.join(out_dir, "truth.npz")
    truth = TruthTrajectory.load(path)
    if target is not None:
        truth = with_target_file(truth, target, path)
    mu, gg = onboard_physics(truth, path)
    sel = slice(0, None, filter_stride(truth.t_s, mcfg.rate_hz))
    chaser = chaser_states(truth.chaser_r_m, truth.chaser_rdot_m_s, truth.chaser_theta_rad,
                           truth.chaser_thetadot_rad_s)[sel]
    z_true, base = truth_measurements(mcfg.kind, truth.corners_C_m[sel], truth.visible[sel], truth.corners_px[sel],
                                      truth.in_frame[sel])
    target = truth_target(truth.config, path)
    check_truth_keypoints(truth, target, path)
    return CampaignTruth(truth.t_s[sel], truth.x[sel], chaser, z_true, base, mu, gg, target)


def block_task(out_dir: str, cfg_json: str, b: int) -> dict:
    """Runner task: filter and reduce block b of the campaign in out_dir, write blocks/block-NNNN.npz
    atomically, return its manifest entry {index, run_start, run_stop, file, sha256, wall_s}."""

    t0 = time.perf_counter()
    cfg = from_dict(MonteCarloConfig, json.loads(cfg_json))
    a, z = cfg.block_range(b)
    arrays = filter_block(load_campaign_truth(out_dir, cfg.measurement, cfg.target), cfg, a, z)
    path = os.path.join(out_dir, block_name(b))
    save_npz(path, arrays)
    return {"index": b, "run_start": a, "run_stop": z, "file": block_name(b), "sha256": sha256_file(path),
            "wall_s": time.perf_counter() - t0}


def filter_block(tr: CampaignTruth, cfg: MonteCarloConfig, run_start: int, run_stop: int) -> dict:
    """Filter runs [run_start, run_stop) and reduce them chunk by chunk. Returns the block file's arrays:
    CampaignSums.to_arrays() (over all T steps), run_<key> per-run summaries (stats.RunSummary fields over the
    settled steps), sample_err (S, T, 12) and sample_norms (S, T, 4) of the block's runs below sample_runs."""

    fcfg, n = cfg.filter, run_stop - run_start
    inp = make_run_inputs(tr.x_true[0], tr.t_s, tr.z_true, tr.base, cfg.measurement, fcfg.P0, cfg.seed, n,
                          first_run=run_start, init_error_scale=cfg.init_error_scale)
    setup = make_setup(fcfg, cfg.measurement.kind, mu_m3_s2=tr.mu_m3_s2, gravity_gradient=tr.gravity_gradient,
                       target=tr.target)
    R_c = np.broadcast_to(inp.R_c, inp.z.shape[:-1] + inp.R_c.shape[-2:])
    state = init_state(inp.x0_hat, fcfg.P0, tr.t_s[0], tr.chaser[0], fcfg)
    T, n_sample = len(tr.t_s), max(0, min(run_stop, cfg.sample_runs) - run_start)
    acc = RunAccumulator(n, settled_mask(tr.t_s, cfg.settle_time_s))
    sums, nees_rt = [], np.empty((n, T))
    sample_err, sample_norms = np.empty((n_sample, T, N_STATE)), np.empty((n_sample, T, 4))
    for k0 in range(0, T, CHUNK_STEPS):
        ks = range(k0, min(T, k0 + CHUNK_STEPS))
        x_hat, P = np.empty((n, len(ks), N_STATE)), np.empty((n, len(ks), N_STATE, N_STATE))
        nis, dof = np.empty((n, len(ks))), np.empty((n, len(ks)), dtype=np.int64)
        for j, k in enumerate(ks):
            state = filter_step(state, Measurement(tr.t_s[k], tr.chaser[k], inp.z[:, k], inp.mask[:, k], R_c[:, k]),
                                setup)
            x_hat[:, j], P[:, j], nis[:, j], dof[:, j] = state.mean, state.cov, state.nis, state.dof
        x_true = np.broadcast_to(tr.x_true[k0:k0 + len(ks)], x_hat.shape)
        e_state = chart_error(x_true, x_hat, fcfg.sigma_chart)  # in the chart of P
        sums.append(reduce_runs(x_true, x_hat, P, nis, dof, np.zeros(n, dtype=bool), e_state=e_state))
        nees_rt[:, ks.start:ks.stop] = acc.add(ks, x_true, x_hat, P, nis, dof, e_state)
        if n_sample:
            sample_err[:, ks.start:ks.stop] = component_errors(x_true[:n_sample], x_hat[:n_sample])
            sample_norms[:, ks.start:ks.stop] = block_error_norms(x_true[:n_sample], x_hat[:n_sample])
    diverged = diverged_against_truth(state.diverged, nees_rt, fcfg)
    out = _join_chunks(sums, run_start, run_stop, diverged)
    out.update({f"run_{k}": v for k, v in vars(acc.result(x_true[:, -1], x_hat[:, -1], diverged)).items()})
    out[ALONE_KEY] = nis_alarms_alone(diverged, nees_rt, fcfg)  # flagged diverged by the filter alone
    out.update(sample_err=sample_err, sample_norms=sample_norms)
    return out


def _join_chunks(sums: list, run_start: int, run_stop: int, diverged: np.ndarray) -> dict:
    """CampaignSums arrays of consecutive time chunks of the same runs, joined along time."""

    joined = CampaignSums(run_start, run_stop, run_stop - run_start,
                          **{k: np.concatenate([getattr(s, k) for s in sums]) for k in CampaignSums.ARRAYS},
                          n_diverged=int(np.count_nonzero(diverged)))
    return joined.to_arrays()


def settled_mask(t_s: np.ndarray, settle_s: float) -> np.ndarray:
    """(T,) bool: the steps at or after t_s[0] + settle_s (stats.settled)."""

    return settled(np.asarray(t_s), settle_s)


def filter_run_history(tr: "CampaignTruth", cfg: MonteCarloConfig, run: int) -> tuple[np.ndarray, np.ndarray]:
    """Run `run` of the campaign filtered alone, as filter_block filters it: its means (T, 12) and covariances
    (T, 12, 12) after every step."""

    fcfg = cfg.filter
    inp = make_run_inputs(tr.x_true[0], tr.t_s, tr.z_true, tr.base, cfg.measurement, fcfg.P0, cfg.seed, 1,
                          first_run=run, init_error_scale=cfg.init_error_scale)
    setup = make_setup(fcfg, cfg.measurement.kind, mu_m3_s2=tr.mu_m3_s2, gravity_gradient=tr.gravity_gradient,
                       target=tr.target)
    R_c = np.broadcast_to(inp.R_c, inp.z.shape[:-1] + inp.R_c.shape[-2:])
    state = init_state(inp.x0_hat, fcfg.P0, tr.t_s[0], tr.chaser[0], fcfg)
    T = len(tr.t_s)
    x_hat, P = np.empty((T, N_STATE)), np.empty((T, N_STATE, N_STATE))
    for k in range(T):
        state = filter_step(state, Measurement(tr.t_s[k], tr.chaser[k], inp.z[:, k], inp.mask[:, k], R_c[:, k]), setup)
        x_hat[k], P[k] = state.mean[0], state.cov[0]
    return x_hat, P
