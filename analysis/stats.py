"""Monte Carlo statistics over R runs of the 12-state filter, per state block, batched and streamable.

State layout: the core's envisat_pose.state (POS, VEL, MRP, RATE; BLOCKS, BLOCK_UNITS, BLOCK_SLICES).
The four blocks and the units the statistics use:

    position          m       rho error in C
    velocity          m/s     rho' error in C
    attitude          rad     small-angle rotation vector (in T) of the MRP error; its norm is the error angle
    angular_velocity  rad/s   w_r error in T

Errors are x_hat - x_true with the truth's MRP first brought to the estimate's set (`align_mrp`): the filter's
covariance P lives on the estimate's set, so NEES and Mahalanobis distances use that set. An MRP difference dp
at p is the rotation vector dtheta = B(p)^-1 dp (p' = B(p) w), |dtheta| = 4 |dp| / (1 + p.p): 4 |dp| only near
p = 0, 2 |dp| at |p| = 1. The same map turns the filter's MRP covariance into a rotation-vector covariance.

Containment: a component is inside when |e_i| <= 3 sigma_i (probability 0.9973 for a consistent Gaussian
filter); a 3-D block is inside when its Mahalanobis distance e^T P_b^-1 e <= chi2.ppf(0.9973, 3) = 14.16, the
3-sigma-equivalent probability of a 3-D Gaussian.

Streaming: `reduce_runs` turns a block of runs into `CampaignSums` (sums over its runs, per time step, no
covariance kept); `merge_sums` / `SumsFolder` fold blocks in run-index order whatever order they arrive in,
so a campaign's result is bitwise the same for any worker count or completion order; `finalize` gives the
statistics over time.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from envisat_pose.attitude import align_mrp, mrp_error_angle_rad, mrp_kinematics_matrix
from envisat_pose.gates import chi2_gate, chi2_quantile
from envisat_pose.state import BLOCK_SLICES, BLOCK_UNITS, BLOCKS, MRP, N_STATE, POS, RATE, VEL, block_sums

P_3SIGMA = 0.9973002039367398  # P(|N(0,1)| <= 3)
MAHALANOBIS_3SIGMA_3D = chi2_gate(P_3SIGMA, 3)  # 14.156 for a 3-D block
P_BAND = (0.025, 0.975)  # two-sided 95 % chi-square band


# ---------------------------------------------------------------- errors in the statistics' units

def state_errors(x_true: np.ndarray, x_hat: np.ndarray) -> np.ndarray:
    """x_hat - x_true with the truth's MRP on the estimate's set (the set of P). (..., 12) -> (..., 12).

    The MRP part stays an MRP difference (dimensionless): use it with P (NEES, Mahalanobis).
    """
    x_true = np.broadcast_to(x_true, np.shape(x_hat))
    e = np.asarray(x_hat, dtype=float) - x_true
    e[..., MRP] = x_hat[..., MRP] - align_mrp(x_true[..., MRP], x_hat[..., MRP])
    return e


def mrp_to_rotvec_matrix(p_mrp: np.ndarray) -> np.ndarray:
    """M(p) = B(p)^-1 = 16 / (1 + p.p)^2 B(p)^T, mapping an MRP difference at p to a rotation vector, rad.

    B B^T = ((1 + p.p) / 4)^2 I, hence the closed-form inverse. (..., 3) -> (..., 3, 3).
    """
    p = np.asarray(p_mrp, dtype=float)
    pp = np.einsum("...i,...i->...", p, p)[..., None, None]
    return 16.0 / (1.0 + pp) ** 2 * np.swapaxes(mrp_kinematics_matrix(p), -1, -2)


def display_transform(p_ref: np.ndarray) -> np.ndarray:
    """The (..., 12, 12) linear map from the state's error to the statistics' units: identity except the MRP
    block, which is M(p_ref) (MRP difference -> rotation vector, rad)."""
    M = mrp_to_rotvec_matrix(p_ref)
    A = np.broadcast_to(np.eye(N_STATE), M.shape[:-2] + (N_STATE, N_STATE)).copy()
    A[..., MRP, MRP] = M
    return A


def component_errors(x_true: np.ndarray, x_hat: np.ndarray) -> np.ndarray:
    """Per-component errors in the statistics' units (attitude as a rotation vector, rad). (..., 12)."""
    e = state_errors(x_true, x_hat)
    e[..., MRP] = np.einsum("...ij,...j->...i", mrp_to_rotvec_matrix(x_hat[..., MRP]), e[..., MRP])
    return e


def component_cov(P: np.ndarray, x_hat: np.ndarray) -> np.ndarray:
    """The filter's covariance in the statistics' units: A P A^T with A = display_transform(p_hat). (..., 12, 12)."""
    A = display_transform(x_hat[..., MRP])
    return A @ P @ np.swapaxes(A, -1, -2)


def block_error_norms(x_true: np.ndarray, x_hat: np.ndarray) -> np.ndarray:
    """|error| per block: m, m/s, the exact attitude error angle (rad), rad/s. (..., 12) -> (..., 4)."""
    e = state_errors(x_true, x_hat)
    return np.stack([np.linalg.norm(e[..., POS], axis=-1), np.linalg.norm(e[..., VEL], axis=-1),
                     mrp_error_angle_rad(x_hat[..., MRP], align_mrp(x_true[..., MRP], x_hat[..., MRP])),
                     np.linalg.norm(e[..., RATE], axis=-1)], axis=-1)


def block_mahalanobis_sq(e_state: np.ndarray, P: np.ndarray) -> np.ndarray:
    """e_b^T P_b^-1 e_b per block (e from `state_errors`, P the filter's). (..., 12), (..., 12, 12) -> (..., 4).

    Invariant under the MRP -> rotation-vector map, so it is taken in the state's own coordinates.
    """
    out = []
    for s in BLOCK_SLICES:
        e = e_state[..., s]
        out.append(np.einsum("...i,...i->...", e, np.linalg.solve(P[..., s, s], e[..., None])[..., 0]))
    return np.stack(out, axis=-1)


def nees_of_errors(e_state: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Normalized estimation error squared e^T P^-1 e (12 dof). (..., 12), (..., 12, 12) -> (...,)."""
    return np.einsum("...i,...i->...", e_state, np.linalg.solve(P, e_state[..., None])[..., 0])


def chi2_mean_bounds(dof_total: np.ndarray | float, n: np.ndarray | float, p: tuple = P_BAND) -> np.ndarray:
    """Two-sided band of a mean of n chi-square terms whose dofs add to dof_total: chi2.ppf(p, dof_total) / n.

    NEES over R runs: chi2_mean_bounds(12 R, R). Broadcasts; (...,) -> (..., 2); NaN where n or dof is 0.
    """
    dof_total, n = np.asarray(dof_total, dtype=float), np.asarray(n, dtype=float)
    ok = (dof_total > 0) & (n > 0)
    lo = chi2_quantile(p[0], np.where(ok, dof_total, 1.0)) / np.where(ok, n, 1.0)
    hi = chi2_quantile(p[1], np.where(ok, dof_total, 1.0)) / np.where(ok, n, 1.0)
    return np.where(ok[..., None], np.stack([lo, hi], axis=-1), np.nan)


# ---------------------------------------------------------------- streaming sums over runs

@dataclass(frozen=True)
class CampaignSums:
    """Sums over the runs [run_start, run_stop) of a campaign, per time step. No covariance is kept.

    n_runs: runs summed. sq_norm: (T, 4) sum of |e_b|^2 (block_error_norms squared). err, sq_err: (T, 12) sum
    of the component errors and of their squares (statistics' units). filt_var: (T, 12) sum of the filter's
    variances (diagonal of component_cov). inside_comp: (T, 12) runs with |e_i| <= 3 sigma_i. inside_block:
    (T, 4) runs with block Mahalanobis distance <= MAHALANOBIS_3SIGMA_3D. nees: (T,) sum of the 12-dof NEES.
    nis: (T,) sum of the NIS over runs with a measurement; nis_dof: (T,) sum of their dofs; nis_runs: (T,) how
    many. n_diverged: runs flagged diverged.
    """

    run_start: int
    run_stop: int
    n_runs: int
    sq_norm: np.ndarray
    err: np.ndarray
    sq_err: np.ndarray
    filt_var: np.ndarray
    inside_comp: np.ndarray
    inside_block: np.ndarray
    nees: np.ndarray
    nis: np.ndarray
    nis_dof: np.ndarray
    nis_runs: np.ndarray
    n_diverged: int

    ARRAYS = ("sq_norm", "err", "sq_err", "filt_var", "inside_comp", "inside_block", "nees", "nis", "nis_dof",
              "nis_runs")

    def to_arrays(self) -> dict:
        """A flat dict of arrays (for save_npz); `from_arrays` inverts it."""
        d = {k: getattr(self, k) for k in self.ARRAYS}
        d["counts"] = np.array([self.run_start, self.run_stop, self.n_runs, self.n_diverged], dtype=np.int64)
        return d

    @classmethod
    def from_arrays(cls, d: dict) -> CampaignSums:
        start, stop, n, n_div = (int(v) for v in d["counts"])
        return cls(start, stop, n, **{k: np.asarray(d[k]) for k in cls.ARRAYS}, n_diverged=n_div)


def reduce_runs(x_true: np.ndarray, x_hat: np.ndarray, P: np.ndarray, nis: np.ndarray, nis_dof: np.ndarray,
                diverged: np.ndarray, run_start: int = 0, e_state: np.ndarray | None = None) -> CampaignSums:
    """Reduce a block of runs to sums over its runs (the heavy part: solves with P happen here, once).

    x_true, x_hat (R, T, 12); P (R, T, 12, 12); nis (R, T); nis_dof (R, T) measured components per step
    (0: no update); diverged (R,) bool. The runs are campaign runs [run_start, run_start + R). e_state (R, T, 12):
    the errors in P's chart, for NEES and the blocks' Mahalanobis distances (a filter's other chart of the sigma
    points: filtering.ukf.chart_error); None: state_errors, the additive chart.
    """
    R = x_hat.shape[0]
    e_state = state_errors(x_true, x_hat) if e_state is None else e_state
    e = component_errors(x_true, x_hat)
    var = np.diagonal(component_cov(P, x_hat), axis1=-2, axis2=-1)
    norms = block_error_norms(x_true, x_hat)
    nis_dof = np.asarray(nis_dof)
    measured = nis_dof > 0
    return CampaignSums(
        run_start=int(run_start), run_stop=int(run_start) + R, n_runs=R,
        sq_norm=(norms**2).sum(0), err=e.sum(0), sq_err=(e**2).sum(0), filt_var=var.sum(0),
        inside_comp=(e**2 <= 9.0 * var).sum(0).astype(np.int64),
        inside_block=(block_mahalanobis_sq(e_state, P) <= MAHALANOBIS_3SIGMA_3D).sum(0).astype(np.int64),
        nees=nees_of_errors(e_state, P).sum(0), nis=np.where(measured, nis, 0.0).sum(0),
        nis_dof=np.where(measured, nis_dof, 0).sum(0).astype(np.int64),
        nis_runs=measured.sum(0).astype(np.int64), n_diverged=int(np.count_nonzero(diverged)))


def _add(a: CampaignSums, b: CampaignSums) -> CampaignSums:
    """a + b for adjacent blocks (a.run_stop == b.run_start)."""
    if a.run_stop != b.run_start:
        raise ValueError(f"runs [{a.run_start}, {a.run_stop}) and [{b.run_start}, {b.run_stop}) are not adjacent")
    return dataclasses.replace(a, run_stop=b.run_stop, n_runs=a.n_runs + b.n_runs,
                               n_diverged=a.n_diverged + b.n_diverged, **{k: getattr(a, k) + getattr(b, k) for k in CampaignSums.ARRAYS})


def merge_sums(parts) -> CampaignSums:
    """Fold blocks in run-index order (a left fold from the lowest run): the same bits for any input order.

    Blocks must tile a contiguous range of runs (a gap or an overlap, e.g. a block counted twice, raises).
    """
    parts = sorted(parts, key=lambda s: s.run_start)
    if not parts:
        raise ValueError("no blocks to merge")
    acc = parts[0]
    for s in parts[1:]:
        acc = _add(acc, s)
    return acc


class SumsFolder:
    """Streaming `merge_sums`: add blocks as they finish, in any order; it folds the contiguous prefix of runs
    at once and holds only the blocks that arrived early. `result()` is bitwise `merge_sums(all blocks)`."""

    def __init__(self, first_run: int = 0):
        self._next = first_run
        self._acc: CampaignSums | None = None
        self._pending: dict[int, CampaignSums] = {}

    def add(self, part: CampaignSums) -> None:
        if part.run_start < self._next or part.run_start in self._pending:
            raise ValueError(f"block starting at run {part.run_start} was already added")
        self._pending[part.run_start] = part
        while self._next in self._pending:
            s = self._pending.pop(self._next)
            self._acc = s if self._acc is None else _add(self._acc, s)
            self._next = s.run_stop

    @property
    def runs_folded(self) -> int:
        """Runs folded so far (the contiguous prefix)."""
        return 0 if self._acc is None else self._acc.n_runs

    def result(self) -> CampaignSums:
        if self._pending or self._acc is None:
            raise ValueError(f"runs missing before run {self._next} (pending blocks at {sorted(self._pending)})")
        return self._acc


# ---------------------------------------------------------------- statistics over time

@dataclass(frozen=True)
class CampaignStats:
    """Statistics over R runs, per time step, in the statistics' units (module docstring).

    rmse_block (T, 4): sqrt(mean over runs of |e_b|^2) (attitude: the error angle). filter_3sigma (T, 12):
    3 sqrt(mean over runs of the filter's variance); filter_3sigma_block (T, 4): 3 sqrt(mean trace of the block).
    mean_err (T, 12); sample_3sigma (T, 12): 3 x the sample standard deviation over runs (ddof 1);
    sample_3sigma_block (T, 4): 3 sqrt(trace of the sample covariance of the block). inside_comp (T, 12),
    inside_block (T, 4): share of runs inside the filter's 3-sigma. nees_mean (T,) with nees_bounds (2,), the
    95 % band of a mean of R chi2(12). nis_mean (T,): mean NIS over runs with a measurement (NaN: none);
    nis_bounds (T, 2). n_runs, n_diverged.
    """

    n_runs: int
    n_diverged: int
    rmse_block: np.ndarray
    filter_3sigma: np.ndarray
    filter_3sigma_block: np.ndarray
    mean_err: np.ndarray
    sample_3sigma: np.ndarray
    sample_3sigma_block: np.ndarray
    inside_comp: np.ndarray
    inside_block: np.ndarray
    nees_mean: np.ndarray
    nees_bounds: np.ndarray
    nis_mean: np.ndarray
    nis_bounds: np.ndarray


def finalize(s: CampaignSums) -> CampaignStats:
    """Statistics over time from the sums (the variance from sums of e and e^2: exact enough while the mean error
    is below ~1e4 standard deviations)."""
    n = s.n_runs
    mean = s.err / n
    var = np.maximum(s.sq_err - s.err * mean, 0.0) / (n - 1) if n > 1 else np.full_like(mean, np.nan)
    vb = block_sums(var)
    fb = block_sums(s.filt_var)
    with np.errstate(invalid="ignore", divide="ignore"):
        nis_mean = np.where(s.nis_runs > 0, s.nis / np.maximum(s.nis_runs, 1), np.nan)
    return CampaignStats(
        n_runs=n, n_diverged=s.n_diverged, rmse_block=np.sqrt(s.sq_norm / n),
        filter_3sigma=3.0 * np.sqrt(s.filt_var / n), filter_3sigma_block=3.0 * np.sqrt(fb / n), mean_err=mean,
        sample_3sigma=3.0 * np.sqrt(var), sample_3sigma_block=3.0 * np.sqrt(vb),
        inside_comp=s.inside_comp / n, inside_block=s.inside_block / n, nees_mean=s.nees / n,
        nees_bounds=chi2_mean_bounds(N_STATE * n, n), nis_mean=nis_mean, nis_bounds=chi2_mean_bounds(s.nis_dof, s.nis_runs))


def campaign_stats(x_true, x_hat, P, nis, nis_dof, diverged) -> CampaignStats:
    """All runs at once: finalize(reduce_runs(...)). Shapes as in `reduce_runs`."""
    return finalize(reduce_runs(x_true, x_hat, P, nis, nis_dof, diverged))


def settled(t_s: np.ndarray, settle_s: float) -> np.ndarray:
    """(T,) bool: steps at or after t_s[0] + settle_s (the converged part of a run)."""
    return t_s >= t_s[0] + settle_s


def nees_bands(n_runs: int, n_steps: int) -> dict:
    """The two 95 % bands of a mean NEES over n_runs runs of n_steps steps each: `nees_bounds` as if every run-step
    were independent, chi2(12 n) / n with n = n_runs n_steps, and `nees_run_bounds` as if each run gave one
    sample, chi2(12 R) / R (campaign_summary says which holds; pipelines.campaigns.lines.nees_band words them)."""
    n_rs = n_runs * n_steps
    return {"nees_bounds": [float(b) for b in chi2_mean_bounds(N_STATE * n_rs, n_rs)],
            "nees_run_bounds": [float(b) for b in chi2_mean_bounds(N_STATE * n_runs, n_runs)]}


def campaign_summary(s: CampaignSums, t_s: np.ndarray, settle_s: float = 0.0) -> dict:
    """Scalars over the settled steps, per block (dicts keyed by BLOCKS): RMSE over run-steps, share of run-steps
    inside the filter's 3-sigma (block Mahalanobis), and the mean NEES with two 95 % bands: `nees_bounds` as if
    every run-step were independent (too narrow: errors are correlated in time) and `nees_run_bounds` as if each
    run gave one sample, chi2(12 R) / R (the wide end: a run's steps are not one draw either); a consistent
    campaign lies within the second. Plain floats (JSON-ready)."""
    k = settled(t_s, settle_s)
    n_rs = s.n_runs * int(k.sum())
    dof_nis = int(s.nis_dof[k].sum())
    nis_lo, nis_hi = chi2_mean_bounds(dof_nis, int(s.nis_runs[k].sum()))
    return {
        "n_runs": s.n_runs, "n_diverged": s.n_diverged, "settle_s": float(settle_s),
        "rmse": {b: float(np.sqrt(s.sq_norm[k, i].sum() / n_rs)) for i, b in enumerate(BLOCKS)},
        "units": dict(zip(BLOCKS, BLOCK_UNITS)),
        "inside_3sigma_share": {b: float(s.inside_block[k, i].sum() / n_rs) for i, b in enumerate(BLOCKS)},
        "nees_mean": float(s.nees[k].sum() / n_rs), **nees_bands(s.n_runs, int(k.sum())),
        "nis_mean": float(s.nis[k].sum() / max(int(s.nis_runs[k].sum()), 1)),
        "nis_mean_per_dof": float(s.nis[k].sum() / dof_nis) if dof_nis else float("nan"),
        "nis_bounds": [float(nis_lo), float(nis_hi)],
    }


# ---------------------------------------------------------------- per run

@dataclass(frozen=True)
class RunSummary:
    """One row per run (concatenate blocks of runs with `concat_run_summaries`).

    rms_block (R, 4): RMS over the settled steps of |e_b| (attitude: the angle), statistics' units.
    final_block (R, 4): |e_b| at the last step. max_block (R, 4): largest |e_b| over the settled steps.
    inside_share (R, 4): share of settled steps inside the filter's 3-sigma (block Mahalanobis).
    nees_mean (R,): mean NEES over the settled steps. nis_per_dof (R,): sum of NIS / sum of dofs (1 when
    consistent; NaN without measurements). diverged (R,) bool.
    """

    rms_block: np.ndarray
    final_block: np.ndarray
    max_block: np.ndarray
    inside_share: np.ndarray
    nees_mean: np.ndarray
    nis_per_dof: np.ndarray
    diverged: np.ndarray


class RunAccumulator:
    """RunSummary streamed over time chunks of the same R runs (a campaign's block never holds all its
    covariances): sums over the settled steps of |e_b|^2, max |e_b|, steps inside 3-sigma, NEES, NIS and its
    dofs. settled: (T,) bool over the whole run (`settled`)."""

    def __init__(self, R: int, settled: np.ndarray):
        self.settled = settled
        self.sq = np.zeros((R, 4))
        self.max = np.zeros((R, 4))
        self.inside = np.zeros((R, 4), dtype=np.int64)
        self.nees = np.zeros(R)
        self.nis = np.zeros(R)
        self.dof = np.zeros(R, dtype=np.int64)
        self.steps = 0

    def add(self, ks: range, x_true, x_hat, P, nis, nis_dof, e_state=None) -> np.ndarray:
        """Fold the steps ks of the runs: x_true, x_hat (R, K, 12), P (R, K, 12, 12), nis and nis_dof (R, K);
        e_state (R, K, 12) the errors in P's chart (None: state_errors, as reduce_runs). Returns the NEES of every
        step of the chunk (R, K) (a divergence monitor reads it)."""
        e_state = state_errors(x_true, x_hat) if e_state is None else e_state
        nees_rk = nees_of_errors(e_state, P)
        k = self.settled[ks.start:ks.stop]
        if k.any():
            norms = block_error_norms(x_true[:, k], x_hat[:, k])
            self.sq += (norms**2).sum(1)
            self.max = np.maximum(self.max, norms.max(1))
            self.inside += (block_mahalanobis_sq(e_state[:, k], P[:, k]) <= MAHALANOBIS_3SIGMA_3D).sum(1)
            self.nees += nees_rk[:, k].sum(1)
            measured = np.asarray(nis_dof)[:, k] > 0
            self.nis += np.where(measured, nis[:, k], 0.0).sum(1)
            self.dof += np.where(measured, nis_dof[:, k], 0).sum(1)
            self.steps += int(k.sum())
        return nees_rk

    def result(self, x_true_last, x_hat_last, diverged) -> RunSummary:
        """The summary of the folded steps; x_true_last, x_hat_last (R, 12) the runs' last step."""
        steps = max(self.steps, 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            nis_per_dof = np.where(self.dof > 0, self.nis / np.maximum(self.dof, 1), np.nan)
        return RunSummary(
            rms_block=np.sqrt(self.sq / steps), final_block=block_error_norms(x_true_last, x_hat_last),
            max_block=self.max, inside_share=self.inside / steps, nees_mean=self.nees / steps,
            nis_per_dof=nis_per_dof, diverged=np.asarray(diverged, dtype=bool))


def run_summary(t_s, x_true, x_hat, P, nis, nis_dof, diverged, settle_s: float = 0.0) -> RunSummary:
    """Per-run summary over the steps at or after t_s[0] + settle_s. Shapes as in `reduce_runs`; t_s (T,) s.
    The whole run as one chunk of `RunAccumulator`."""
    x_true = np.broadcast_to(x_true, np.shape(x_hat))
    acc = RunAccumulator(x_hat.shape[0], settled(np.asarray(t_s), settle_s))
    acc.add(range(0, x_hat.shape[1]), x_true, x_hat, P, nis, np.asarray(nis_dof))
    return acc.result(x_true[:, -1], x_hat[:, -1], diverged)


def concat_run_summaries(parts) -> RunSummary:
    """Concatenate per-run summaries of blocks given in run order."""
    parts = list(parts)
    return RunSummary(**{f.name: np.concatenate([getattr(p, f.name) for p in parts])
                         for f in dataclasses.fields(RunSummary)})
