"""The fused numba kernels (filtering/fast.py, FilterConfig.kernel = "fast", the default) against the numpy
filter (kernel = "reference", filtering/ukf.py) on the configurations the filter tests cover.

Two kinds of agreement:
- one step from the same prior: the mean relative to max(|x_i|, sigma_i) and the covariance relative to
  sqrt(P_ii P_jj), within UPDATE_TOL for an update and PREDICT_TOL for a prediction. The difference
  is round-off: summation order, a Cholesky solve where numpy inverts S, and D = t^1.5 (the kernel's
  t sqrt(t) and numpy's t ** 1.5, SVML's pow on an AVX-512 machine, differ in the last place for ~18 % of
  inputs). Most components agree to ~1e-15; the worst is the radial velocity, whose two gravity terms
  mu (r + x) / D and mu / r^2 (~8 m/s^2 each) cancel to ~1e-6 m/s^2, so one ulp of D is ~1e-11 of its
  standard deviation after a step;
- whole runs: every decision equal (corners used, gate rejections, visibility drops, dof, divergence flags,
  repairs) and the estimates no further from the reference than the reference itself moves when its P0 is
  changed by one unit in the last place. The first update of a run (P0's metre and 2.5 deg against 2 cm
  corners) cancels ~8 digits in P - K S K^T, so any two implementations of it, and the reference against
  itself after a 1-ulp change of its input, differ by ~1e-8 there; a fixed 1e-12 over a whole run would
  only hold for bit-identical arithmetic.
"""

import dataclasses
import os
import subprocess
import sys

import numpy as np
import pytest

from envisat_pose.filtering import fast, ukf
from envisat_pose.filtering.estimator import FilterConfig, make_setup, run_filter
from envisat_pose.filtering.measurements import swap_corners
from envisat_pose.filtering.montecarlo import MeasurementConfig, inputs_from_truth
from envisat_pose.state import MRP

T_STEPS = 150
R_RUNS = 4
# Round-off bounds that hold on any x86-64 machine: measured on an AVX-512 machine 1.0e-11 at most for a prediction
# (radial velocity, see above) and 5e-13 for an update (markers3d; 1.5e-13 pixels+range, 7e-14 pixels); numpy's pow
# (SVML on AVX-512 only), OpenBLAS's kernels and the fastmath Cholesky's vector width follow the CPU, so the bounds
# leave 50x and 20x; a wrong equation or a missed term moves the step by far more than 1e-8 of a sigma.
PREDICT_TOL = 5e-10
UPDATE_TOL = 1e-11


def _sigma_errors(x, P, x_ref, P_ref):
    """Largest |x - x_ref| / max(|x_ref|, sigma) and |P - P_ref| / (sigma_i sigma_j), sigma from P_ref's
    diagonal: relative errors, where a component near zero counts relative to its standard deviation."""
    sd = np.sqrt(np.einsum("...ii->...i", P_ref))
    ex = np.abs(x - x_ref) / np.maximum(np.abs(x_ref), sd)
    eP = np.abs(P - P_ref) / (sd[..., :, None] * sd[..., None, :])
    return float(ex.max()), float(eP.max())


def _run(tr, chaser_of, kind, cfg, mcfg_kw=None, seed=5, fault=None, P0=None):
    mcfg = MeasurementConfig(kind=kind, **(mcfg_kw or {}))
    inp = inputs_from_truth(tr, mcfg, cfg.P0, seed=seed, n_runs=R_RUNS, sel=slice(0, T_STEPS))
    if fault is not None:
        fault(inp)
    out = {}
    for kernel, p0 in (("reference", cfg.P0), ("fast", cfg.P0), ("reference_ulp", P0)):
        c = dataclasses.replace(cfg, kernel=kernel.split("_")[0])
        out[kernel] = run_filter(inp.x0_hat, p0, tr.t_s[:T_STEPS], chaser_of(tr)[:T_STEPS], inp.z, inp.mask,
                                 inp.R_c, kind, c)
    return inp, out


def _swap(tr):
    steps = (tr.t_s[:T_STEPS] >= 60.0) & (tr.t_s[:T_STEPS] < 70.0)
    i, j = np.flatnonzero(tr.visible[:T_STEPS][steps].all(axis=0))[:2]

    def fault(inp):
        inp.z = swap_corners(inp.z, steps, i, j)
    return fault


def _nan(inp):
    inp.z[0, 30:33] = np.nan          # a broken detector in run 0
    inp.z[1, 40, 2] = np.nan          # one NaN corner in run 1


CONFIGS = {
    "markers3d": ("markers3d", {}, {}, None),
    "pixels": ("pixels", {}, {}, None),
    "pixels+range": ("pixels+range", {}, {}, None),
    "adaptive R and Q": ("markers3d", {"adaptive_r": True, "adaptive_q": True}, {}, None),
    "gating, swapped corner": ("markers3d", {}, {}, "swap"),
    "outage": ("markers3d", {}, {"outages_s": ((50.0, 90.0),), "failure_prob": 0.2}, None),
    "NaN input": ("markers3d", {"divergence_window": 10, "divergence_settle_steps": 20}, {}, "nan"),
}


@pytest.mark.parametrize("name", list(CONFIGS))
def test_fast_and_reference_agree_over_whole_runs(truth_600, chaser_of, name):
    kind, cfg_kw, mcfg_kw, fault = CONFIGS[name]
    # the kernels themselves, one update a step: the split (filtering/step_update.py) calls the same kernel again
    # on the runs it splits, and 16 partial updates of the first step move the reference's own round-off
    # further than one ulp of P0 does (test_the_split_runs_agree)
    cfg = FilterConfig(split_max=1, **cfg_kw)
    fault = {"swap": _swap(truth_600), "nan": _nan, None: None}[fault]
    u = np.random.default_rng(0).choice([-1.0, 1.0], 12)
    P0_ulp = cfg.P0 * (1.0 + 2.0**-52 * u)  # the reference's own sensitivity to one ulp of its input
    inp, res = _run(truth_600, chaser_of, kind, cfg, mcfg_kw, fault=fault, P0=P0_ulp)
    ref, fst, ulp = res["reference"], res["fast"], res["reference_ulp"]
    for field in ("n_meas", "dof", "rejected", "dropped", "diverged", "repaired"):
        np.testing.assert_array_equal(getattr(fst, field), getattr(ref, field), err_msg=f"{name}: {field}")
    ex, eP = _sigma_errors(fst.x_hat, fst.P, ref.x_hat, ref.P)
    ux, uP = _sigma_errors(ulp.x_hat, ulp.P, ref.x_hat, ref.P)
    print(f"{name}: fast - reference {ex:.2e} sigma (x), {eP:.2e} (P); reference after 1 ulp of P0: "
          f"{ux:.2e}, {uP:.2e}")
    assert ex <= 10 * max(ux, 1e-12) and eP <= 10 * max(uP, 1e-12)
    assert ex < 1e-6 and eP < 1e-6
    np.testing.assert_allclose(fst.nis, ref.nis, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(fst.r_scale, ref.r_scale, rtol=1e-9)
    assert np.isfinite(fst.x_hat).all() and np.isfinite(fst.P).all()
    if name == "gating, swapped corner":
        assert fst.rejected.sum() >= 5
    if name == "outage":
        assert (fst.n_meas[:, 50:90] == 0).all()
    if name == "NaN input":
        assert (fst.n_meas[0, 30:33] == 0).all() and fst.n_meas[1, 40] == ref.n_meas[1, 40]
    if name == "adaptive R and Q":
        assert np.abs(fst.r_scale - 1.0).min() > 0.1  # the scale really moved in every run


@pytest.mark.parametrize("kind", ["markers3d", "pixels"])
def test_the_split_runs_agree(truth_600, chaser_of, kind):
    """With the first step split (the default split_max: P0 is hundreds of times wider than the noise), every
    decision equal and the estimates within 1e-6 of a sigma (measured: 6.5e-10 markers3d, 1.9e-10 pixels; one
    update a step 2e-8: the first update's cancellation in P - K S K^T, which partial updates avoid)."""
    cfg = FilterConfig()
    _, res = _run(truth_600, chaser_of, kind, cfg, P0=cfg.P0)
    ref, fst = res["reference"], res["fast"]
    for field in ("n_meas", "dof", "rejected", "dropped", "diverged", "repaired"):
        np.testing.assert_array_equal(getattr(fst, field), getattr(ref, field), err_msg=f"{kind}: {field}")
    ex, eP = _sigma_errors(fst.x_hat, fst.P, ref.x_hat, ref.P)
    print(f"{kind}, split: fast - reference {ex:.2e} sigma (x), {eP:.2e} (P)")
    assert ex < 1e-6 and eP < 1e-6


def _prior(tr, chaser_of, kind="markers3d", k=60):
    """A converged prior of R runs at step k: the reference filter run to k, its posterior."""
    cfg = FilterConfig(kernel="reference")
    inp = inputs_from_truth(tr, MeasurementConfig(kind=kind), cfg.P0, seed=2, n_runs=R_RUNS, sel=slice(0, k + 2))
    res = run_filter(inp.x0_hat, cfg.P0, tr.t_s[:k + 1], chaser_of(tr)[:k + 1], inp.z[:, :k + 1],
                     inp.mask[:, :k + 1], inp.R_c, kind, cfg)
    return inp, res.x_hat[:, k], res.P[:, k]


@pytest.mark.parametrize("dt_s,gravity_gradient", [(1.0, False), (1.0, True), (3.0, False), (2.5, True)])
def test_one_predict_equals_the_reference(truth_600, chaser_of, dt_s, gravity_gradient):
    _, mean, cov = _prior(truth_600, chaser_of)
    mean = mean.copy()
    mean[0, MRP] *= 0.999 / np.linalg.norm(mean[0, MRP])  # near |p| = 1: sigma points on both sets
    c = chaser_of(truth_600)[60]
    cfg = FilterConfig()
    setup = make_setup(cfg, "markers3d", gravity_gradient=gravity_gradient)
    Q = cfg.Q(dt_s) * np.array([1.0, 10.0, 1.0, 1.0])[:, None, None]  # per run, as after an outage
    m_ref, P_ref = ukf.predict(mean, cov, c, dt_s, Q, setup.weights, setup.J_T, setup.mu_m3_s2, 1.0,
                               gravity_gradient)
    m_fast, P_fast = fast.predict_fused(mean, cov, c, dt_s, Q, setup, 1.0)
    ex, eP = _sigma_errors(m_fast, P_fast, m_ref, P_ref)
    assert ex < PREDICT_TOL and eP < PREDICT_TOL, (ex, eP)
    assert (np.linalg.norm(m_fast[:, MRP], axis=-1) <= 1.0).all()


@pytest.mark.parametrize("kind,visibility_from", [("markers3d", "spread"), ("pixels", "spread"),
                                                  ("pixels+range", "spread"), ("pixels", "mean")])
def test_one_update_equals_the_reference(truth_600, chaser_of, kind, visibility_from):
    tr = truth_600
    inp, mean, cov = _prior(tr, chaser_of, kind)
    cfg = FilterConfig(adaptive_r=True, visibility_from=visibility_from)
    setup = make_setup(cfg, kind)
    k = 61
    z = inp.z[:, k].copy()
    seen = np.flatnonzero(inp.mask[0, k])
    z[0, seen[0]] += 0.5 if kind != "pixels" else 40.0   # an outlier for the gate in run 0
    R_c = np.broadcast_to(inp.R_c, z.shape + (z.shape[-1],))
    r_scale = np.array([1.0, 2.0, 0.5, 1.0])
    thr = np.array([setup.gate_threshold, setup.gate_threshold, setup.gate_threshold, np.inf])
    o = fast.update_fused(mean, cov, z, inp.mask[:, k], R_c, r_scale, thr, True, setup)
    mk = inp.mask[:, k] & setup.visible_by_prior(mean, cov)
    m_ref, P_ref, info = ukf.update(mean, cov, z, mk, R_c * r_scale[:, None, None, None], setup.hx,
                                    setup.weights, thr)
    np.testing.assert_array_equal(o["mask_k"], mk)
    np.testing.assert_array_equal(o["accepted"], info.accepted)
    assert mk[0, seen[0]] and not o["accepted"][0, seen[0]]  # the gate took the outlier out
    np.testing.assert_array_equal(o["dof"], info.dof)
    ex, eP = _sigma_errors(o["mean"], o["cov"], m_ref, P_ref)
    assert ex < UPDATE_TOL and eP < UPDATE_TOL, (ex, eP)
    np.testing.assert_allclose(o["nis"], info.nis, rtol=1e-10)
    np.testing.assert_allclose(o["Ky"], np.einsum("rij,rj->ri", info.K, info.y), rtol=1e-9,
                               atol=1e-12 * np.abs(o["Ky"]).max())
    np.testing.assert_allclose(o["yy"], np.einsum("ri,ri->r", info.y, info.y), rtol=1e-12)
    np.testing.assert_allclose(o["trPzz"], np.einsum("rii->r", info.Pzz_state), rtol=1e-12)


def test_a_run_that_needs_a_repair_is_the_reference_s(truth_600, chaser_of):
    """A covariance that is not positive definite: the kernel hands that run to the numpy filter, which
    repairs it (eigenvalue floor); the other runs stay in the kernel. Both give the reference's result."""
    inp, mean, cov = _prior(truth_600, chaser_of)
    cov = cov.copy()
    cov[1, 0, 1] = cov[1, 1, 0] = 2.0 * np.sqrt(cov[1, 0, 0] * cov[1, 1, 1])  # |correlation| 2: indefinite
    cfg = FilterConfig()
    setup = make_setup(cfg, "markers3d")
    c = chaser_of(truth_600)[60]
    m_ref, P_ref = ukf.predict(mean, cov, c, 1.0, cfg.Q(1.0), setup.weights, setup.J_T)
    m_fast, P_fast = fast.predict_fused(mean, cov, c, 1.0, cfg.Q(1.0), setup)
    np.testing.assert_array_equal(m_fast[1], m_ref[1])
    np.testing.assert_array_equal(P_fast[1], P_ref[1])
    ex, eP = _sigma_errors(m_fast[[0, 2, 3]], P_fast[[0, 2, 3]], m_ref[[0, 2, 3]], P_ref[[0, 2, 3]])
    assert ex < PREDICT_TOL and eP < PREDICT_TOL


def test_the_fast_filter_is_deterministic_and_batch_independent(truth_600, chaser_of):
    tr = truth_600
    cfg = FilterConfig(adaptive_r=True, adaptive_q=True)
    inp = inputs_from_truth(tr, MeasurementConfig(kind="pixels", failure_prob=0.1), cfg.P0, seed=4, n_runs=3,
                            sel=slice(0, 80))
    args = (tr.t_s[:80], chaser_of(tr)[:80])
    a = run_filter(inp.x0_hat, cfg.P0, *args, inp.z, inp.mask, inp.R_c, "pixels", cfg)
    b = run_filter(inp.x0_hat, cfg.P0, *args, inp.z, inp.mask, inp.R_c, "pixels", cfg)
    assert a.x_hat.tobytes() == b.x_hat.tobytes() and a.P.tobytes() == b.P.tobytes()
    one = run_filter(inp.x0_hat[1:2], cfg.P0, *args, inp.z[1:2], inp.mask[1:2], inp.R_c, "pixels", cfg)
    assert one.x_hat.tobytes() == a.x_hat[1:2].tobytes() and one.P.tobytes() == a.P[1:2].tobytes()


def test_an_unknown_kernel_is_refused():
    with pytest.raises(ValueError, match="kernel"):
        make_setup(FilterConfig(kernel="gpu"), "markers3d")
    from envisat_pose.config import ConfigError

    with pytest.raises(ConfigError, match="kernel"):
        FilterConfig(kernel="numpy").validate()


def _files_under(folder):
    return {os.path.join(d, f): os.stat(os.path.join(d, f)).st_mtime_ns
            for d, _, names in os.walk(folder) for f in names}


@pytest.mark.parametrize("numba_cache_dir", [False, True])
def test_the_compiled_cache_goes_to_the_user_cache_folder(tmp_path, numba_cache_dir):
    """A fresh process that imports the kernels and runs one writes its compiled cache under
    $XDG_CACHE_HOME/envisat-pose/numba (or numba's own NUMBA_CACHE_DIR when set) and nothing inside the package."""
    package = os.path.dirname(fast.__file__)
    before = _files_under(package)
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(XDG_CACHE_HOME=str(tmp_path / "xdg"), PYTHONDONTWRITEBYTECODE="1")
    if numba_cache_dir:
        env["NUMBA_CACHE_DIR"] = str(tmp_path / "numba")
    code = ("from envisat_pose.filtering import fast\nimport numpy as np\n"
            "assert fast._sq(3.0) == 9.0\nprint(fast.cache_dir())\n")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    want = tmp_path / ("numba" if numba_cache_dir else os.path.join("xdg", "envisat-pose", "numba"))
    assert out.stdout.strip() == str(want)
    written = [f for f in _files_under(str(want)) if f.endswith((".nbi", ".nbc"))]
    assert any(os.path.basename(f).startswith("fast._sq-") for f in written), written
    assert _files_under(package) == before


@pytest.mark.parametrize("numba_cache_dir", [False, True])
def test_an_unwritable_cache_folder_goes_to_a_private_one_never_the_package(tmp_path, monkeypatch, numba_cache_dir):
    """Where cache_dir() cannot be written (a read-only home without XDG_CACHE_HOME, an unwritable
    NUMBA_CACHE_DIR), the kernels' cache goes to a temporary folder of the process: not the package's own folder
    (numba's next locator), and no import error where that one is read-only too (numba's chain ends in one)."""
    from numba.core import config as numba_config

    blocked = tmp_path / "a_file"
    blocked.write_text("")  # a folder under a file cannot be made, not even by root
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocked / "xdg"))
    monkeypatch.setattr(numba_config, "CACHE_DIR", str(blocked / "numba") if numba_cache_dir else "")
    package = os.path.dirname(os.path.abspath(fast.__file__))
    locator = fast._UserCacheLocator.from_function(fast._sq.py_func, fast.__file__)
    assert locator is not None
    path = locator.get_cache_path()
    assert not path.startswith(package) and not path.startswith(str(blocked))
    assert os.path.dirname(path) == fast._private_cache_dir() and os.path.isdir(path)
    assert (os.stat(fast._private_cache_dir()).st_mode & 0o077) == 0  # the process's own
