"""A filter step's measurement update (estimator.filter_step's): the kernel's update (visibility check, gate,
unscented update), and, for a run whose prior is far wider than its measurement, the same measurement again in
partial updates.

The split, a recursive update in its simplest form (after Zanetti, "Recursive update filtering for nonlinear
estimation", IEEE Trans. Automatic Control 57(6), 2012): a run whose prior spreads the measured components
ratio = tr(Pzz) / tr(R) times wider than their noise takes n = ceil(ratio / split_gain) updates (at most
split_max) from its prior, on the corners the single update accepted, whose shares of the information grow
geometrically, each update's prior the same few times wider than its noise (split_factors; equal shares made the
first of 0.1 mm markers' 16 updates 1.25e7 times wider than its noise, the campaign overconfident). With a
linear model that is the single update's posterior (the shares of R^-1 add up to it); with the camera's it is a
better one: each partial update draws its sigma points about the previous one's posterior, where the single
update spreads them over the whole prior, whose lateral metre at 50 m moves the image by ~40 px and turns the
line of sight by a degree, which a small target's few pixels then read as attitude and range.

Where it acts: the first step of a campaign, whose P0 (1 m, 10 deg) is hundreds of times wider in the measured
components than their noise. A tracked step's prior is narrower than its noise: one update, as before. The
NIS, the gate's and the visibility check's decisions and the adaptive noise's statistics stay the single
update's (the measurement against the prior).
"""

from __future__ import annotations

import numpy as np

from envisat_pose.filtering.ukf import update


def uses_fused_kernel(cfg) -> bool:
    """Whether a filter of FilterConfig cfg runs filtering/fast.py's fused numba kernels: kernel 'fast' with the
    additive chart (they run no other: sigma_chart 'rotation' or 'screw' runs the numpy filter, predict and
    update alike)."""
    return cfg.kernel == "fast" and cfg.sigma_chart == "additive"


def kernel_update(mean: np.ndarray, cov: np.ndarray, z: np.ndarray, measured: np.ndarray, R_c: np.ndarray,
                  r_scale: np.ndarray, thr, vis_check: bool, setup) -> dict:
    """One measurement update of R runs: filtering/fast.py's fused kernel where uses_fused_kernel(setup.cfg), else
    the numpy filter of filtering/ukf.py in the config's chart: the visibility check (vis_check: the corners
    setup.visible_by_prior hides dropped), the gate (thr: a
    bound per run, or None for none), the unscented update with R_c * r_scale. Returns a dict of mean, cov, nis, dof, accepted
    (R, K), mask_k (R, K) (the corners the gate saw), Ky (R, 12) = K y, yy (R,) = y.y, trPzz (R,) = tr(Pzz) over
    the used components, indefinite (R,) bool (and with the fast kernel suspect: the runs it redid in numpy)."""
    if uses_fused_kernel(setup.cfg):
        from envisat_pose.filtering import fast  # numba compiles (or loads its cache) on first use

        return fast.update_fused(mean, cov, z, measured, R_c, r_scale, thr, vis_check, setup)
    Rk = R_c * r_scale[:, None, None, None]
    mask_k = measured
    if vis_check:
        mask_k = mask_k & setup.visible_by_prior(mean, cov)
    mean, cov, info = update(mean, cov, z, mask_k, Rk, setup.hx, setup.weights, thr, setup.cfg.sigma_chart)
    return {"mean": mean, "cov": cov, "nis": info.nis, "dof": info.dof, "accepted": info.accepted, "mask_k": mask_k,
            "Ky": np.einsum("rij,rj->ri", info.K, info.y), "yy": np.einsum("ri,ri->r", info.y, info.y),
            "trPzz": np.einsum("rii->r", info.Pzz_state), "indefinite": info.indefinite}


def split_counts(tr_pzz: np.ndarray, tr_r: np.ndarray, gain: float, most: int) -> np.ndarray:
    """(R,) int: the partial updates each run's measurement takes, ceil(ratio / gain) within [1, most], where
    ratio = tr_pzz / tr_r: how many times the prior's spread in the measured components (tr Pzz) exceeds their
    noise (tr R), both over the components used. No measurement, or a non-finite ratio: 1."""
    ratio = np.where(tr_r > 0, tr_pzz / np.where(tr_r > 0, tr_r, 1.0), 0.0)
    ratio = np.where(np.isfinite(ratio), ratio, 0.0)
    return np.clip(np.ceil(ratio / float(gain)), 1, max(int(most), 1)).astype(np.int64)


def split_factors(ratio: np.ndarray, gain: float, most: int) -> np.ndarray:
    """(R, most) the noise multiplier of each run's partial updates (update k takes R x factor, the information
    fraction 1 / factor; the fractions sum to 1), 0 past a run's last; ratio (R,) as split_counts reads it.

    A run of n = split_counts' updates (ceil(ratio / gain) within [1, most]) takes them with fractions that grow
    geometrically, f_k = (q - 1) q^(k-1) / ratio with q = (1 + ratio)^(1 / n): each adds q - 1 times the
    information gathered before it, so every update's prior is q - 1 times wider than its noise (a linear model's:
    the least that n updates can make their widest; below the gain, since (1 + gain)^n - 1 >= n gain >= ratio,
    up to a ratio of (1 + gain)^most - 1 past most, 4.6e16 for the defaults). n equal shares made the first
    update ratio / n times wider and the later ones narrower (2 cm markers from P0 past most: 250 against the
    gain's 10; 0.1 mm markers: 1.25e7), and their widest jumped from the gain to (1 + ratio)^(1 / most) - 1 where
    ratio / gain crossed most."""
    ratio = np.asarray(ratio, dtype=float)
    most = max(int(most), 1)
    n = split_counts(ratio, np.ones_like(ratio), gain, most)
    out = np.where(np.arange(most) < n[:, None], 1.0, 0.0)
    split = np.flatnonzero(n > 1)
    if len(split) == 0:
        return out
    k = np.arange(most)
    log_q = np.log1p(ratio[split]) / n[split]
    log_f = np.log(np.expm1(log_q))[:, None] + log_q[:, None] * k - np.log(ratio[split])[:, None]
    f = np.where(k < n[split][:, None], np.exp(log_f), 0.0)
    out[split] = np.where(f > 0, f.sum(-1, keepdims=True) / np.where(f > 0, f, 1.0), 0.0)
    return out


def measurement_update(mean: np.ndarray, cov: np.ndarray, z: np.ndarray, measured: np.ndarray, R_c: np.ndarray,
                       r_scale: np.ndarray, thr, setup) -> dict:
    """filter_step's update of R runs from their prior (mean (R, 12), cov (R, 12, 12)): kernel_update with the
    config's visibility check and the gate thr, then the runs that split_counts splits updated again from the
    prior in that many partial updates (module docstring). z (R, K, m); measured (R, K); R_c (R, K, m, m);
    r_scale (R,). Returns kernel_update's dict, its mean and cov replaced for the split runs whose partial
    updates all succeeded (the others keep the single update's), and splits (R,) int: the updates each run took."""
    cfg = setup.cfg
    up = kernel_update(mean, cov, z, measured, R_c, r_scale, thr, cfg.visibility_check, setup)
    accepted = np.asarray(up["accepted"], dtype=bool)
    tr_r = np.einsum("rkii->r", R_c * accepted[..., None, None]) * r_scale
    tr_pzz = np.asarray(up["trPzz"], dtype=float)
    counts = split_counts(tr_pzz, tr_r, cfg.split_gain, cfg.split_max)
    counts = np.where(np.asarray(up["indefinite"], dtype=bool), 1, counts)
    idx = np.flatnonzero(counts > 1)
    up["splits"] = counts
    if len(idx) == 0:
        return up
    n = counts[idx]
    factors = split_factors(tr_pzz[idx] / tr_r[idx], cfg.split_gain, cfg.split_max)
    m_i, P_i = mean[idx].copy(), cov[idx].copy()
    z_i, acc_i, R_i = z[idx], accepted[idx], R_c[idx]
    failed = np.zeros(len(idx), dtype=bool)
    for step in range(int(n.max())):
        sub = np.flatnonzero((n > step) & ~failed)
        if len(sub) == 0:
            break
        r_i = r_scale[idx][sub] * factors[sub, step]
        res = kernel_update(m_i[sub], P_i[sub], z_i[sub], acc_i[sub], R_i[sub], r_i, None, False, setup)
        m_i[sub], P_i[sub] = res["mean"], res["cov"]
        failed[sub] |= np.asarray(res["indefinite"], dtype=bool)
    failed |= ~(np.isfinite(m_i).all(-1) & np.isfinite(P_i).all((-1, -2)))
    keep = idx[~failed]
    up["mean"], up["cov"] = np.array(up["mean"], copy=True), np.array(up["cov"], copy=True)
    up["mean"][keep], up["cov"][keep] = m_i[~failed], P_i[~failed]
    counts[idx[failed]] = 1
    return up
