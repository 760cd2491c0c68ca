"""The batched UKF in fused numba kernels: the same filter as filtering/ukf.py, one run at a time in compiled code.

Why numba (measured on the 2-core development machine, 2026-11-24): the numpy filter spends its ~65-90 us per
run-step (1000 runs) on ~150 array operations over (runs, 25 sigma points, 12) temporaries, each a pass
through memory, not on arithmetic (one run-step is ~9e4 floating-point operations, 1.7 us at this core's
dgemm rate). The RK4 propagation alone, the largest part: numpy 29 us per run, the same model in torch
(float64, CPU, one thread) 35 us per run: torch keeps numpy's shape (one pass per operation) and adds its
dispatch. A compiled loop over runs keeps one run's sigma points in registers and L1 for the whole step:
the same propagation here takes ~1.2 us, a whole run-step ~9 us (bench/ukf_speed.py). numba compiles plain
Python loops with no build step (its llvmlite wheel ships LLVM), and with fastmath off its floating-point
operations are IEEE and deterministic: the same inputs give the same bytes (one function, the Cholesky
factorization, lets LLVM reassociate its sums so they vectorize: still the same bytes for the same inputs on
a machine). Compiled code is cached in the user's cache folder (numba's cache=True, located by
`cache_dir()`: NUMBA_CACHE_DIR when set, else $XDG_CACHE_HOME/envisat-pose/numba or ~/.cache/envisat-pose/numba;
never inside the installed package): the first use on a machine compiles for ~10 s, later processes load it in
~0.3 s. Where that folder cannot be written (a read-only home, an unwritable NUMBA_CACHE_DIR) the cache goes to a
private temporary folder of the process, removed when it ends: each process compiles again, none fails.

The kernels do exactly the reference's steps, in the reference's order where the order matters for
round-off (the RK4 stage sums, the sigma-point mean, the symmetrization of P):
- predict: sigma points from chol((n + lam) P), RK4 sub-steps of the filter's model (filtering/dynamics.py,
  with the gravity-gradient torque when asked) with the MRP switched to |p| <= 1 between sub-steps, MRPs
  brought to the central point's set before the weighted mean, the mean switched to |p| <= 1, residuals on
  the mean's set, P = sum Wc r r^T + Q, symmetrized;
- update: sigma points from the prior, the visibility check (FilterConfig.visibility_from: a measured corner is
  dropped where the prior mean, or the mean and every sigma point, hide it; ENVISAT's exact face test in the
  kernel, another target's fast visibility table looked up in numpy before the kernel), the
  measurement model of the measured keypoints (the setup's K: markers3d, pixels with the guarded pinhole,
  pixels+range),
  per-corner chi-square gate, innovation covariance S, gain, mean and covariance, the shadow switch with its
  Jacobian, symmetrization.
Differences from the numpy filter are round-off only: the update works on the measured components (the numpy
filter gives the others zero innovation and unit variance, which is the same update) and solves with the
Cholesky factor of S where numpy inverts S; the weighted sums of sigma points go through the same BLAS
products numpy's matmul uses; D = t^1.5 is t sqrt(t) (a call to pow would keep the model's loop from
vectorizing; numpy's t ** 1.5 is itself SVML's pow on an AVX-512 machine, not the C library's: all three
round differently in the last place). A run whose step needs a covariance repair (a Cholesky factor
that fails: not positive definite, or not finite) is flagged, and the caller recomputes that run with the
numpy filter (filtering/ukf.py), so repairs and roll-backs are the reference's own.
"""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile

import numpy as np
from numba import njit
from numba.core import caching as _caching
from numba.core import config as _numba_config

from envisat_pose.filtering import ukf
from envisat_pose.filtering.measurements import MIN_DEPTH_M
from envisat_pose.geometry import load_geometry
from envisat_pose.state import MRP, N_STATE, POS, RATE, VEL

# the kernels' equations index the 12-state of envisat_pose.state directly (rho 0-2, rho' 3-5, p 6-8, w_r 9-11)
if (POS, VEL, MRP, RATE) != (slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12)):
    raise ImportError("filtering/fast.py is written for the state layout (rho, rho', p, w_r); "
                      "envisat_pose.state changed it: update the kernels")


def cache_dir() -> str:
    """The folder our compiled kernels are cached in: numba's own NUMBA_CACHE_DIR when the user set it, else
    $XDG_CACHE_HOME/envisat-pose/numba, else ~/.cache/envisat-pose/numba. Never the package's folder (an
    installed package may be read-only, or shared by users)."""
    if _numba_config.CACHE_DIR:
        return _numba_config.CACHE_DIR
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "envisat-pose", "numba")


_PRIVATE_CACHE: list[str] = []  # the process's temporary cache folder, made on first need


def _private_cache_dir() -> str:
    """A temporary folder of this process's own (mkdtemp: mode 0700, a fresh name), removed when it exits: the
    cache where cache_dir() cannot be written, so that numba never falls back to the package's folder, nor fails
    to import the kernels for want of any writable folder (its own chain ends in an error)."""
    if not _PRIVATE_CACHE:
        _PRIVATE_CACHE.append(tempfile.mkdtemp(prefix="envisat-pose-numba-"))
        atexit.register(shutil.rmtree, _PRIVATE_CACHE[0], True)
    return _PRIVATE_CACHE[0]


class _UserCacheLocator(_caching._SourceFileBackedLocatorMixin, _caching._CacheLocator):
    """numba's cache locator for this file's kernels only: cache_dir() (the user cache folder, or numba's own
    NUMBA_CACHE_DIR when set), under a sub-folder named for this file's path (two installs never share entries),
    else a temporary folder of the process where that one cannot be written. Other files are left to numba's
    own locators."""

    def __init__(self, py_func, py_file, folder: str):
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        self._cache_path = os.path.join(folder, self.get_suitable_cache_subpath(py_file))

    def get_cache_path(self):
        return self._cache_path

    @classmethod
    def from_function(cls, py_func, py_file):
        if os.path.abspath(py_file) != os.path.abspath(__file__):
            return None
        for folder in (cache_dir, _private_cache_dir):
            try:
                self = cls(py_func, py_file, folder())
                self.ensure_cache_path()
                return self
            except OSError:  # not writable (or no temporary folder at all): the next, then numba's own
                continue
        return None


_CACHE_IMPL = getattr(_caching, "CacheImpl", None) or _caching._CacheImpl  # _CacheImpl in older numba
if _UserCacheLocator not in _CACHE_IMPL._locator_classes:
    _CACHE_IMPL._locator_classes = [_UserCacheLocator, *_CACHE_IMPL._locator_classes]


KIND_CODES = {"markers3d": 0, "pixels": 1, "pixels+range": 2}
_P0 = MRP.start  # first MRP component in the 12-state (envisat_pose.state.MRP)
_JIT = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")
# the update's parts (update_kernel calls them in order), compiled without numba's reference counting (the
# internal `_nrt=False`: they allocate nothing) and handed whole arrays and the run's index: with reference counts
# on each array they are handed (compiled as usual, or inlined into the kernel: 5-12 % slower) or a row view per
# run (a count each) the update was slower than in one function; so it is ~6 % faster than the one 249-line
# function was (both timed in one process on the same inputs). Only the kernel calls np.dot (its out= needs the
# counts).
_JIT_PART = dict(_JIT, _nrt=False)
# sigma points as columns of a flat (12, _SP) array, row i at [i * _SP:(i + 1) * _SP]: a row stride known when
# compiling lets LLVM prove the rows apart and vectorize the loops over sigma points (25 used, 7 padding)
_SP = 32


# ---------------------------------------------------------------- small dense helpers

@njit(**_JIT)
def _sq(x):
    """x * x, as numpy's x ** 2 (a call to pow would keep the loops around it from vectorizing)."""
    return x * x


@njit(**_JIT)
def _chol(A, U, n):
    """Cholesky factor of the symmetric A[:n, :n] as U = L^T (row k of U = column k of the lower factor L,
    A = L L^T), zero below the diagonal; False when A is not positive definite (or not finite). Row by row,
    so that the inner loops run along rows (vectorized); each entry's sum over k runs in ascending order."""
    for j in range(n):
        for i in range(j):
            U[j, i] = 0.0
        for i in range(j, n):
            U[j, i] = A[j, i]
        for k in range(j):
            ukj = U[k, j]
            for i in range(j, n):
                U[j, i] -= U[k, i] * ukj
        s = U[j, j]
        if not s > 0.0:
            return False
        d = np.sqrt(s)
        U[j, j] = d
        for i in range(j + 1, n):
            U[j, i] = U[j, i] / d
    return True


@njit(cache=True, nogil=True, fastmath={"reassoc", "contract"}, error_model="numpy")
def _chol_lower(A, L, n):
    """Lower Cholesky factor of the symmetric A[:n, :n] into L (row-major, zero above the diagonal), its sums
    as dot products along rows (reassociated so that they vectorize: round-off differs from _chol's); False
    when A is not positive definite (or not finite)."""
    for j in range(n):
        for i in range(j + 1, n):
            L[j, i] = 0.0
        acc = 0.0
        for k in range(j):
            acc += L[j, k] * L[j, k]
        s = A[j, j] - acc
        if not s > 0.0:
            return False
        d = np.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            acc = 0.0
            for k in range(j):
                acc += L[i, k] * L[j, k]
            L[i, j] = (A[i, j] - acc) / d
    return True


@njit(**_JIT)
def _dcm(p, G):
    """Gamma(p) = I - a1 [p x] + a2 [p x]^2 (envisat_pose.attitude.mrp_to_dcm) into G (3, 3)."""
    pp = p[0] * p[0] + p[1] * p[1] + p[2] * p[2]
    a1 = 4.0 * (1.0 - pp) / _sq(1.0 + pp)
    a2 = 8.0 / _sq(1.0 + pp)
    s01, s02, s10, s12, s20, s21 = -p[2], p[1], p[2], -p[0], -p[1], p[0]
    # [p x]^2, row by column
    q00 = s01 * s10 + s02 * s20
    q01 = s02 * s21
    q02 = s01 * s12
    q10 = s12 * s20
    q11 = s10 * s01 + s12 * s21
    q12 = s10 * s02
    q20 = s21 * s10
    q21 = s20 * s01
    q22 = s20 * s02 + s21 * s12
    G[0, 0] = (1.0 - a1 * 0.0) + a2 * q00
    G[0, 1] = (0.0 - a1 * s01) + a2 * q01
    G[0, 2] = (0.0 - a1 * s02) + a2 * q02
    G[1, 0] = (0.0 - a1 * s10) + a2 * q10
    G[1, 1] = (1.0 - a1 * 0.0) + a2 * q11
    G[1, 2] = (0.0 - a1 * s12) + a2 * q12
    G[2, 0] = (0.0 - a1 * s20) + a2 * q20
    G[2, 1] = (0.0 - a1 * s21) + a2 * q21
    G[2, 2] = (1.0 - a1 * 0.0) + a2 * q22


@njit(**_JIT)
def _shadow(p):
    """|p| <= 1 in place: p -> -p/(p.p) where p.p > 1 (envisat_pose.attitude.mrp_shadow)."""
    pp = p[0] * p[0] + p[1] * p[1] + p[2] * p[2]
    if pp > 1.0:
        p[0], p[1], p[2] = -p[0] / pp, -p[1] / pp, -p[2] / pp


# ---------------------------------------------------------------- the model (filtering/dynamics.py)

@njit(**_JIT)
def _rates(Y, c, J, Jinv, mu, gg, dY):
    """dY = state_rate(Y, c) for every column (sigma point) of the flat Y (12, _SP): translation (sheet,
    section 4), MRP kinematics, relative attitude dynamics, with the gravity-gradient torque when gg. c (4,)
    the chaser's stage state."""
    r, rd, thd = c[0], c[1], c[3]
    thdd = -2.0 * rd * thd / r
    thd2 = _sq(thd)
    mu_r2 = mu / _sq(r)
    J00, J01, J02, J10, J11, J12, J20, J21, J22 = (J[0, 0], J[0, 1], J[0, 2], J[1, 0], J[1, 1], J[1, 2],
                                                   J[2, 0], J[2, 1], J[2, 2])
    I00, I01, I02, I10, I11, I12, I20, I21, I22 = (Jinv[0, 0], Jinv[0, 1], Jinv[0, 2], Jinv[1, 0], Jinv[1, 1],
                                                   Jinv[1, 2], Jinv[2, 0], Jinv[2, 1], Jinv[2, 2])
    for s in range(_SP):
        x, yy, z = Y[0 * _SP + s], Y[1 * _SP + s], Y[2 * _SP + s]
        xd, yd = Y[3 * _SP + s], Y[4 * _SP + s]
        t = _sq(r + x) + _sq(yy) + _sq(z)
        D = t * np.sqrt(t)                                            # t^1.5
        dY[0 * _SP + s], dY[1 * _SP + s], dY[2 * _SP + s] = Y[3 * _SP + s], Y[4 * _SP + s], Y[5 * _SP + s]
        dY[3 * _SP + s] = 2.0 * thd * yd + thdd * yy + thd2 * x - mu * (r + x) / D + mu_r2
        dY[4 * _SP + s] = -2.0 * thd * xd - thdd * x + thd2 * yy - mu * yy / D
        dY[5 * _SP + s] = -mu * z / D
        # Gamma(p) = I - a1 [p x] + a2 [p x]^2 (envisat_pose.attitude.mrp_to_dcm)
        p0, p1, p2 = Y[6 * _SP + s], Y[7 * _SP + s], Y[8 * _SP + s]
        pp = p0 * p0 + p1 * p1 + p2 * p2
        a1 = 4.0 * (1.0 - pp) / _sq(1.0 + pp)
        a2 = 8.0 / _sq(1.0 + pp)
        G00 = 1.0 + a2 * (-p2 * p2 + -p1 * p1)
        G01 = (0.0 - a1 * -p2) + a2 * (p1 * p0)
        G02 = (0.0 - a1 * p1) + a2 * (-p2 * -p0)
        G10 = (0.0 - a1 * p2) + a2 * (-p0 * -p1)
        G11 = 1.0 + a2 * (p2 * -p2 + -p0 * p0)
        G12 = (0.0 - a1 * -p0) + a2 * (p2 * p1)
        G20 = (0.0 - a1 * -p1) + a2 * (p0 * p2)
        G21 = (0.0 - a1 * p0) + a2 * (-p1 * -p2)
        G22 = 1.0 + a2 * (-p1 * p1 + p0 * -p0)
        w0, w1, w2 = Y[9 * _SP + s], Y[10 * _SP + s], Y[11 * _SP + s]
        g0, g1, g2 = G02 * thd, G12 * thd, G22 * thd                  # Gamma w_c
        h0, h1, h2 = G02 * thdd, G12 * thdd, G22 * thdd               # Gamma w_c'
        t0, t1, t2 = w0 + g0, w1 + g1, w2 + g2                        # w_t = w_r + Gamma w_c
        j0 = J00 * t0 + J01 * t1 + J02 * t2
        j1 = J10 * t0 + J11 * t1 + J12 * t2
        j2 = J20 * t0 + J21 * t1 + J22 * t2
        c0 = t1 * j2 - t2 * j1                                        # w_t x J w_t
        c1 = t2 * j0 - t0 * j2
        c2 = t0 * j1 - t1 * j0
        if gg:
            # tau = 3 mu / |R|^5 (R x J R), R_T = Gamma (r e_x + rho_C)
            R0 = x + r
            T0 = G00 * R0 + G01 * yy + G02 * z
            T1 = G10 * R0 + G11 * yy + G12 * z
            T2 = G20 * R0 + G21 * yy + G22 * z
            RR = T0 * T0 + T1 * T1 + T2 * T2
            k = 3.0 * mu / (RR * RR * np.sqrt(RR))
            u0 = J00 * T0 + J01 * T1 + J02 * T2
            u1 = J10 * T0 + J11 * T1 + J12 * T2
            u2 = J20 * T0 + J21 * T1 + J22 * T2
            c0 = k * (T1 * u2 - T2 * u1) - c0                        # tau - w_t x J w_t
            c1 = k * (T2 * u0 - T0 * u2) - c1
            c2 = k * (T0 * u1 - T1 * u0) - c2
        else:
            c0, c1, c2 = -c0, -c1, -c2
        dY[9 * _SP + s] = (I00 * c0 + I01 * c1 + I02 * c2) + (w1 * g2 - w2 * g1) - h0   # J^-1 (...) + w_r x G w_c - G w_c'
        dY[10 * _SP + s] = (I10 * c0 + I11 * c1 + I12 * c2) + (w2 * g0 - w0 * g2) - h1
        dY[11 * _SP + s] = (I20 * c0 + I21 * c1 + I22 * c2) + (w0 * g1 - w1 * g0) - h2
        # p' = 1/4 [(1 - p.p) I + 2 [p x] + 2 p p^T] w
        d = 1.0 - pp
        dY[6 * _SP + s] = (0.25 * (d + 2.0 * p0 * p0) * w0 + 0.25 * (2.0 * -p2 + 2.0 * p0 * p1) * w1
                    + 0.25 * (2.0 * p1 + 2.0 * p0 * p2) * w2)
        dY[7 * _SP + s] = (0.25 * (2.0 * p2 + 2.0 * p1 * p0) * w0 + 0.25 * (d + 2.0 * p1 * p1) * w1
                    + 0.25 * (2.0 * -p0 + 2.0 * p1 * p2) * w2)
        dY[8 * _SP + s] = (0.25 * (2.0 * -p1 + 2.0 * p2 * p0) * w0 + 0.25 * (2.0 * p0 + 2.0 * p2 * p1) * w1
                    + 0.25 * (d + 2.0 * p2 * p2) * w2)


@njit(**_JIT)
def _propagate(X, stages, h, J, Jinv, mu, gg, k1, k2, k3, k4, Ys):
    """propagate() of filtering/dynamics.py in place on the columns of the flat X (12, _SP): RK4 sub-steps of
    h seconds with the chaser's stage states stages (n_sub, 4, 4); the MRP switches to |p| <= 1 between
    sub-steps only."""
    N = X.shape[0]
    n_sub = stages.shape[0]
    hh = 0.5 * h
    h6 = h / 6.0
    for st in range(n_sub):
        _rates(X, stages[st, 0], J, Jinv, mu, gg, k1)
        for j in range(N):
            Ys[j] = X[j] + hh * k1[j]
        _rates(Ys, stages[st, 1], J, Jinv, mu, gg, k2)
        for j in range(N):
            Ys[j] = X[j] + hh * k2[j]
        _rates(Ys, stages[st, 2], J, Jinv, mu, gg, k3)
        for j in range(N):
            Ys[j] = X[j] + h * k3[j]
        _rates(Ys, stages[st, 3], J, Jinv, mu, gg, k4)
        for j in range(N):
            X[j] = X[j] + h6 * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j])
        if st < n_sub - 1:
            for s in range(_SP):
                p0, p1, p2 = X[_P0 * _SP + s], X[(_P0 + 1) * _SP + s], X[(_P0 + 2) * _SP + s]
                pp = p0 * p0 + p1 * p1 + p2 * p2
                if pp > 1.0:
                    p0, p1, p2 = -p0 / pp, -p1 / pp, -p2 / pp
                X[_P0 * _SP + s], X[(_P0 + 1) * _SP + s], X[(_P0 + 2) * _SP + s] = p0, p1, p2


@njit(**_JIT)
def _to_cols(sig, X):
    """Sigma points sig (S, n) into the columns of the flat X (n, _SP); the padding columns repeat chi_0."""
    S, n = sig.shape
    for i in range(n):
        for s in range(S):
            X[i * _SP + s] = sig[s, i]
        for s in range(S, _SP):
            X[i * _SP + s] = sig[0, i]


@njit(**_JIT)
def _sigma_points(mean, cov, scale, A, L, sig):
    """Scaled symmetric sigma points chi_0 = x, chi_k = x + L[:, k], chi_(n+k) = x - L[:, k], L L^T = scale P
    (L the lower Cholesky factor).
    sig (2n + 1, n). False when scale P has no Cholesky factor (the caller repairs it with the numpy filter)."""
    n = mean.shape[0]
    for i in range(n):
        for j in range(n):
            A[i, j] = scale * cov[i, j]
    if not _chol_lower(A, L, n):
        return False
    for i in range(n):
        sig[0, i] = mean[i]
    for k in range(n):
        for i in range(n):
            sig[1 + k, i] = mean[i] + L[i, k]
            sig[1 + n + k, i] = mean[i] - L[i, k]
    return True


@njit(**_JIT)
def _finite_pd(P, L, n):
    """Whether P (n, n) is finite and has a Cholesky factor (numpy's repair_cov would leave it as it is)."""
    for i in range(n):
        for j in range(n):
            if not np.isfinite(P[i, j]):
                return False
    return _chol_lower(P, L, n)


# ---------------------------------------------------------------- predict

@njit(**_JIT)
def predict_kernel(mean, cov, Q, stages, h, Wm, Wc, scale, J, Jinv, mu, gg, mean_out, cov_out, ok):
    """UKF time update of R runs (filtering/ukf.predict). mean (R, 12), cov and Q (R, 12, 12); stages
    (n_sub, 4, 4) the chaser at the RK4 stages of each sub-step of h s. Writes mean_out, cov_out; ok (R,) False
    where the step needs the numpy filter's covariance repair."""
    R, n = mean.shape
    S = 2 * n + 1
    A = np.empty((n, n))
    L = np.empty((n, n))
    sig = np.empty((S, n))
    X = np.empty(n * _SP)       # sigma points as columns (flat, see _SP)
    k1, k2, k3, k4, Ys = (np.empty(n * _SP), np.empty(n * _SP), np.empty(n * _SP), np.empty(n * _SP),
                          np.empty(n * _SP))
    al = np.empty((3, _SP))
    m = np.empty(n)
    P = np.empty((n, n))
    rw = np.empty((n, S))
    for r in range(R):
        ok[r] = _sigma_points(mean[r], cov[r], scale, A, L, sig)
        if not ok[r]:
            continue
        _to_cols(sig, X)
        _propagate(X, stages, h, J, Jinv, mu, gg, k1, k2, k3, k4, Ys)
        # x = sum Wm chi, with every MRP on the central point's set (align_mrp)
        q0, q1, q2 = X[_P0 * _SP], X[(_P0 + 1) * _SP], X[(_P0 + 2) * _SP]
        _align_cols(X, q0, q1, q2, al)
        for s in range(S):
            for i in range(n):
                sig[s, i] = al[i - _P0, s] if _P0 <= i < _P0 + 3 else X[i * _SP + s]
        mv = np.dot(Wm, sig)                                      # as numpy's Wm @ s
        for i in range(n):
            m[i] = mv[i]
        pp = m[_P0] * m[_P0] + m[_P0 + 1] * m[_P0 + 1] + m[_P0 + 2] * m[_P0 + 2]
        if pp > 1.0:
            m[_P0], m[_P0 + 1], m[_P0 + 2] = -m[_P0] / pp, -m[_P0 + 1] / pp, -m[_P0 + 2] / pp
        # residuals chi - x, each MRP on the mean's set, as rows of sig
        _align_cols(X, m[_P0], m[_P0 + 1], m[_P0 + 2], al)
        for s in range(S):
            for i in range(n):
                sig[s, i] = (al[i - _P0, s] if _P0 <= i < _P0 + 3 else X[i * _SP + s]) - m[i]
        # P = sum Wc (chi - x)(chi - x)^T + Q (BLAS, as numpy's matmul forms it), symmetrized
        for i in range(n):
            for s in range(S):
                rw[i, s] = sig[s, i] * Wc[s]
        np.dot(rw, sig, P)
        for i in range(n):
            mean_out[r, i] = m[i]
            for j in range(n):
                cov_out[r, i, j] = 0.5 * ((P[i, j] + Q[r, i, j]) + (P[j, i] + Q[r, j, i]))
        ok[r] = _finite_pd(cov_out[r], L, n)


@njit(**_JIT)
def _align_cols(X, q0, q1, q2, al):
    """align_mrp of every column's MRP (rows _P0.._P0+2 of the flat X (12, _SP)) to q, into al (3, _SP)."""
    for s in range(_SP):
        p0, p1, p2 = X[_P0 * _SP + s], X[(_P0 + 1) * _SP + s], X[(_P0 + 2) * _SP + s]
        pp = p0 * p0 + p1 * p1 + p2 * p2
        den = pp if pp > 0.0 else 1.0
        s0, s1, s2 = -p0 / den, -p1 / den, -p2 / den
        ds = np.sqrt(_sq(s0 - q0) + _sq(s1 - q1) + _sq(s2 - q2))
        dp = np.sqrt(_sq(p0 - q0) + _sq(p1 - q1) + _sq(p2 - q2))
        if ds < dp and pp > 0.0:
            al[0, s], al[1, s], al[2, s] = s0, s1, s2
        else:
            al[0, s], al[1, s], al[2, s] = p0, p1, p2


# ---------------------------------------------------------------- update

@njit(**_JIT)
def _dcm_cols(X, Gs):
    """Gamma(p) (envisat_pose.attitude.mrp_to_dcm) of every column's MRP of the flat X (12, _SP), row-major into Gs (9, _SP)."""
    for s in range(_SP):
        p0, p1, p2 = X[_P0 * _SP + s], X[(_P0 + 1) * _SP + s], X[(_P0 + 2) * _SP + s]
        pp = p0 * p0 + p1 * p1 + p2 * p2
        a1 = 4.0 * (1.0 - pp) / _sq(1.0 + pp)
        a2 = 8.0 / _sq(1.0 + pp)
        Gs[0, s] = 1.0 + a2 * (-p2 * p2 + -p1 * p1)
        Gs[1, s] = (0.0 - a1 * -p2) + a2 * (p1 * p0)
        Gs[2, s] = (0.0 - a1 * p1) + a2 * (-p2 * -p0)
        Gs[3, s] = (0.0 - a1 * p2) + a2 * (-p0 * -p1)
        Gs[4, s] = 1.0 + a2 * (p2 * -p2 + -p0 * p0)
        Gs[5, s] = (0.0 - a1 * -p0) + a2 * (p2 * p1)
        Gs[6, s] = (0.0 - a1 * -p1) + a2 * (p0 * p2)
        Gs[7, s] = (0.0 - a1 * p0) + a2 * (-p1 * -p2)
        Gs[8, s] = 1.0 + a2 * (-p1 * p1 + p0 * -p0)


@njit(**_JIT)
def _measure_cols(X, Gs, c, kind, corners_T, cam_R, cam_pos, cam_f, cam_cu, cam_cv, min_depth, out):
    """Corner c measured from the first S columns of the flat X (12, _SP), Gs their Gamma, into out (m, S): markers3d
    rho + Gamma^T v_c (m); pixels the guarded pinhole (px); pixels+range adds |v_C - camera| (m)."""
    v0, v1, v2 = corners_T[c, 0], corners_T[c, 1], corners_T[c, 2]
    S = out.shape[1]
    if kind == 0:
        for s in range(S):
            out[0, s] = X[0 * _SP + s] + (v0 * Gs[0, s] + v1 * Gs[3, s] + v2 * Gs[6, s])
            out[1, s] = X[1 * _SP + s] + (v0 * Gs[1, s] + v1 * Gs[4, s] + v2 * Gs[7, s])
            out[2, s] = X[2 * _SP + s] + (v0 * Gs[2, s] + v1 * Gs[5, s] + v2 * Gs[8, s])
        return
    R00, R01, R02, R10, R11, R12, R20, R21, R22 = (cam_R[0, 0], cam_R[0, 1], cam_R[0, 2], cam_R[1, 0],
                                                   cam_R[1, 1], cam_R[1, 2], cam_R[2, 0], cam_R[2, 1],
                                                   cam_R[2, 2])
    c0, c1, c2 = cam_pos[0], cam_pos[1], cam_pos[2]
    for s in range(S):
        d0 = (X[0 * _SP + s] + (v0 * Gs[0, s] + v1 * Gs[3, s] + v2 * Gs[6, s])) - c0
        d1 = (X[1 * _SP + s] + (v0 * Gs[1, s] + v1 * Gs[4, s] + v2 * Gs[7, s])) - c1
        d2 = (X[2 * _SP + s] + (v0 * Gs[2, s] + v1 * Gs[5, s] + v2 * Gs[8, s])) - c2
        x = d0 * R00 + d1 * R01 + d2 * R02
        y = d0 * R10 + d1 * R11 + d2 * R12
        z = max(d0 * R20 + d1 * R21 + d2 * R22, min_depth)
        out[0, s] = cam_f * x / z + cam_cu
        out[1, s] = cam_f * y / z + cam_cv
        if kind == 2:
            out[2, s] = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)


@njit(**_JIT)
def table_visible_kernel(mean, cell_dir, log_ranges, visible, out):
    """A target's visibility table (envisat_pose.target.VisibilityTable.lookup, the same grid and formulas) read
    from the prior means (R, 12): c_T = -Gamma(p) rho, its cell of the polar x azimuth grid cell_dir (rows, 2 rows)
    -> the direction's row of visible (B, N, K) at the range bin nearest in log (log_ranges (B,)). Writes out (R, K)
    bool (all True where c_T is not finite, as the lookup). O(1) per run: the numpy lookup's matrix product over
    every direction, and its Gamma matrices, were a third of another target's update (bench/target_estimation.py)."""
    G = np.empty((3, 3))
    rows = cell_dir.shape[0]
    for r in range(mean.shape[0]):
        _dcm(mean[r, _P0:_P0 + 3], G)
        c0 = -(G[0, 0] * mean[r, 0] + G[0, 1] * mean[r, 1] + G[0, 2] * mean[r, 2])
        c1 = -(G[1, 0] * mean[r, 0] + G[1, 1] * mean[r, 1] + G[1, 2] * mean[r, 2])
        c2 = -(G[2, 0] * mean[r, 0] + G[2, 1] * mean[r, 1] + G[2, 2] * mean[r, 2])
        if not (np.isfinite(c0) and np.isfinite(c1) and np.isfinite(c2)):
            for c in range(visible.shape[2]):
                out[r, c] = True
            continue
        rng = max(np.sqrt(c0 * c0 + c1 * c1 + c2 * c2), 1e-12)
        lr = np.log(rng)
        b = 0
        for k in range(1, log_ranges.shape[0]):
            if abs(lr - log_ranges[k]) < abs(lr - log_ranges[b]):
                b = k
        i = min(int(np.arccos(min(max(c2 / rng, -1.0), 1.0)) * (rows / np.pi)), rows - 1)
        j = min(int((np.arctan2(c1, c0) + np.pi) * (rows / np.pi)), 2 * rows - 1)
        d = cell_dir[i, j]
        for c in range(visible.shape[2]):
            out[r, c] = visible[b, d, c]


def table_visible(x: np.ndarray, table) -> np.ndarray:
    """table_visible_kernel over states x (..., 12): (..., K) bool."""
    flat = np.ascontiguousarray(np.asarray(x, float).reshape(-1, N_STATE))
    out = np.empty((flat.shape[0], table.visible.shape[2]), dtype=bool)
    table_visible_kernel(flat, table.cell_dir, np.log(table.ranges_m), table.visible, out)
    return out.reshape(np.shape(x)[:-1] + (table.visible.shape[2],))


@njit(**_JIT_PART)
def _measured_corners(measured, r, mask_k, accepted, act):
    """The measured corners of run r (measured (R, K)): writes row r of mask_k (R, K), clears accepted's (R, K),
    lists the corners in act; returns their number."""
    na = 0
    for c in range(measured.shape[1]):
        mask_k[r, c] = measured[r, c]
        accepted[r, c] = False
        if measured[r, c]:
            act[na] = c
            na += 1
    return na


@njit(**_JIT_PART)
def _shown_by_prior(sig, n_pts, act, na, face_n, face_h, face_corners, G, seen, mask_k, r):
    """The visibility check: keeps in act those of its na corners that the box face test (face_n (6, 3), face_h
    (6,), face_corners (6, K) bool) shows from the chaser of any of the first n_pts sigma points (sig (S, 12),
    the mean first: n_pts 1 the mean alone); clears row r of mask_k for the others; returns the number kept."""
    for a in range(na):
        seen[a] = False
    for s in range(n_pts):
        _dcm(sig[s, _P0:_P0 + 3], G)
        cT0 = -(G[0, 0] * sig[s, 0] + G[0, 1] * sig[s, 1] + G[0, 2] * sig[s, 2])
        cT1 = -(G[1, 0] * sig[s, 0] + G[1, 1] * sig[s, 1] + G[1, 2] * sig[s, 2])
        cT2 = -(G[2, 0] * sig[s, 0] + G[2, 1] * sig[s, 1] + G[2, 2] * sig[s, 2])
        for a in range(na):
            if seen[a]:
                continue
            c = act[a]
            for f in range(face_n.shape[0]):
                if face_corners[f, c] and (face_n[f, 0] * cT0 + face_n[f, 1] * cT1 + face_n[f, 2] * cT2
                                           > face_h[f]):
                    seen[a] = True
                    break
    kept = 0
    for a in range(na):
        if seen[a]:
            act[kept] = act[a]
            kept += 1
        else:
            mask_k[r, act[a]] = False
    return kept


@njit(**_JIT_PART)
def _keep_prior(mean, cov, r, mean_out, cov_out, Ky):
    """The posterior of run r set to its prior (mean (R, 12), cov (R, 12, 12)) and K y to zero, before any
    update."""
    n = mean.shape[1]
    for i in range(n):
        mean_out[r, i] = mean[r, i]
        Ky[r, i] = 0.0
        for j in range(n):
            cov_out[r, i, j] = cov[r, i, j]


@njit(**_JIT_PART)
def _predicted_moments(X, mean, r, act, na, mdim, Wm, Wc, kind, corners_T, cam_R, cam_pos, cam_f, cam_cu, cam_cv,
                       min_depth, Gs, al3, zT, zs, zp, Wv):
    """The unscented transform of run r's sigma points (columns of the flat X) through the measurement model of
    its na corners act (filtering/measurements.measure): zp (M,) = sum Wm z_s, dz = z_s - z_pred into zs (S, M),
    and Wv (M + 12, S) = [Wc dz; Wc dx], dx = chi - x with each MRP on the mean's set, so that Wv @ zs is
    [Pzz; Pxz] (the caller's one matrix product through BLAS). zT (M, S) is work space (M = na mdim)."""
    n = mean.shape[1]
    S = zs.shape[0]
    M = na * mdim
    _dcm_cols(X, Gs)
    for a in range(na):
        _measure_cols(X, Gs, act[a], kind, corners_T, cam_R, cam_pos, cam_f, cam_cu, cam_cv, min_depth,
                      zT[a * mdim:(a + 1) * mdim])
    # dx = chi - x with each MRP on the mean's set, weighted by Wc, under the weighted dz in Wv
    _align_cols(X, mean[r, _P0], mean[r, _P0 + 1], mean[r, _P0 + 2], al3)
    for i in range(n):
        mi = mean[r, i]
        if _P0 <= i < _P0 + 3:
            for s in range(S):
                Wv[M + i, s] = (al3[i - _P0, s] - mi) * Wc[s]
        else:
            for s in range(S):
                Wv[M + i, s] = (X[i * _SP + s] - mi) * Wc[s]
    for s in range(S):
        for a in range(M):
            zs[s, a] = zT[a, s]
    for a in range(M):
        zp[a] = 0.0
    for s in range(S):
        ws = Wm[s]
        for a in range(M):
            zp[a] += ws * zs[s, a]
    for s in range(S):
        ws = Wc[s]
        for a in range(M):
            zs[s, a] -= zp[a]                                  # dz = z_s - z_pred
            Wv[a, s] = zs[s, a] * ws


@njit(**_JIT_PART)
def _innovation(z, R_c, r, sr, act, na, mdim, zp, Pzz, y, Sm):
    """Run r's innovation y (M,) = z - z_pred of its corners act (z (R, K, m)), and its covariance Sm (M, M) = Pzz
    plus each corner's R_c (R, K, m, m) x sr (block diagonal)."""
    M = na * mdim
    for ai in range(na):
        ca = act[ai]
        for da in range(mdim):
            a = ai * mdim + da
            y[a] = z[r, ca, da] - zp[a]                        # innovation
            for b in range(M):
                Sm[a, b] = Pzz[a, b]
            for db in range(mdim):                             # + R of the corner (block diagonal)
                Sm[a, ai * mdim + db] += R_c[r, ca, da, db] * sr


@njit(**_JIT_PART)
def _gate(Sm, y, na, mdim, thr, use_gate, comp, act, accepted, r, Sc, Lc, buf):
    """The chi-square gate per corner, y_c^T S_cc^-1 y_c <= thr (a NaN distance fails), when use_gate: the kept
    corners' slots moved to the front of act and marked in row r of accepted (R, K). Returns how many were kept,
    -1 where a corner's S_cc has no Cholesky factor (the numpy filter redoes the run)."""
    keep = 0
    for a in range(na):
        good = True
        if use_gate:
            o = a * mdim
            for i in range(mdim):
                for j in range(mdim):
                    Sc[i, j] = Sm[o + i, o + j]
            if not _chol(Sc, Lc, mdim):
                return -1
            d2 = 0.0
            for i in range(mdim):
                t = y[o + i]
                for k in range(i):
                    t -= Lc[k, i] * buf[k]
                buf[i] = t / Lc[i, i]
                d2 += buf[i] * buf[i]
            good = d2 <= thr
        if good:
            act[keep] = a
            keep += 1
            accepted[r, act_corner(comp, a, mdim)] = True
    return keep


@njit(**_JIT_PART)
def _compact(keep, na, mdim, n, act, comp, y, Sm, Pzz, Pxz, u, Ls, V):
    """y, Sm and V (Mk, 12) = Pxz^T compacted to the keep accepted corners' components, in order (u and Ls work
    space). Returns tr(Pzz) over them."""
    Mk = keep * mdim
    for a in range(keep):
        for d in range(mdim):
            comp[a * mdim + d] = act[a] * mdim + d           # now indexes the measured-corner vectors
    tr = 0.0
    for a in range(Mk):
        tr += Pzz[comp[a], comp[a]]
    if keep < na:
        for a in range(Mk):
            ia = comp[a]
            u[a] = y[ia]
            for b in range(Mk):
                Ls[a, b] = Sm[ia, comp[b]]
            for i in range(n):
                V[a, i] = Pxz[i, ia]
        for a in range(Mk):
            y[a] = u[a]
            for b in range(Mk):
                Sm[a, b] = Ls[a, b]
    else:
        for a in range(Mk):
            for i in range(n):
                V[a, i] = Pxz[i, a]
    return tr


@njit(**_JIT_PART)
def _whiten(Ls, y, Mk, n, u, V):
    """u = L^-1 y and V = L^-1 Pxz^T in place (L = Ls, the lower Cholesky factor of S): K = V^T L^-1, K y = V^T u,
    K S K^T = V^T V, NIS = u.u (forward substitution as row operations: each entry's sum over k in ascending
    order). Returns (NIS, y.y)."""
    for a in range(Mk):
        t = y[a]
        for k in range(a):
            t -= Ls[a, k] * u[k]
        d = Ls[a, a]
        u[a] = t / d
        for k in range(a):
            lak = Ls[a, k]
            for i in range(n):
                V[a, i] -= lak * V[k, i]
        for i in range(n):
            V[a, i] = V[a, i] / d
    ny, yty = 0.0, 0.0
    for a in range(Mk):
        ny += u[a] * u[a]
        yty += y[a] * y[a]
    return ny, yty


@njit(**_JIT_PART)
def _gain_terms(V, u, Mk, r, Ky, Vt):
    """Run r's K y = V^T u into Ky (R, 12), and Vt (12, Mk) = V^T (for K S K^T = V^T V)."""
    n = V.shape[1]
    for i in range(n):
        Ky[r, i] = 0.0
    for a in range(Mk):
        ua = u[a]
        for i in range(n):
            Ky[r, i] += V[a, i] * ua
    for i in range(n):
        for a in range(Mk):
            Vt[i, a] = V[a, i]


@njit(**_JIT_PART)
def _posterior(mean, cov, r, Ky, mean_out, P):
    """Run r's x+ = x + K y into mean_out (R, 12), and P = cov - K S K^T in place (P holds K S K^T)."""
    n = mean.shape[1]
    for i in range(n):
        mean_out[r, i] = mean[r, i] + Ky[r, i]
        for j in range(n):
            P[i, j] = cov[r, i, j] - P[i, j]


@njit(**_JIT_PART)
def _shadow_switch(mean, r, P, Sj):
    """|p| > 1: run r's mean (row r of (R, 12)) to its shadow set, the covariance P (12, 12) with
    S = (2 p p^T - (p.p) I) / (p.p)^2 (Sj work space). Nothing when |p| <= 1."""
    n = mean.shape[1]
    p0, p1, p2 = mean[r, _P0], mean[r, _P0 + 1], mean[r, _P0 + 2]
    pp = p0 * p0 + p1 * p1 + p2 * p2
    if pp <= 1.0:
        return
    pv = (p0, p1, p2)
    for i in range(3):
        for j in range(3):
            Sj[i, j] = (2.0 * pv[i] * pv[j] - (pp if i == j else 0.0)) / _sq(pp)
    _shadow(mean[r, _P0:_P0 + 3])
    for j in range(n):
        b0, b1, b2 = P[_P0, j], P[_P0 + 1, j], P[_P0 + 2, j]
        for i in range(3):
            P[_P0 + i, j] = Sj[i, 0] * b0 + Sj[i, 1] * b1 + Sj[i, 2] * b2
    for i in range(n):
        b0, b1, b2 = P[i, _P0], P[i, _P0 + 1], P[i, _P0 + 2]
        for j in range(3):
            P[i, _P0 + j] = b0 * Sj[j, 0] + b1 * Sj[j, 1] + b2 * Sj[j, 2]


@njit(**_JIT_PART)
def _symmetrized_ok(P, cov_out, mean_out, r, ny, L):
    """Run r's cov_out = (P + P^T) / 2; whether its posterior is usable: the covariance finite and positive
    definite, the NIS and the mean finite."""
    n = P.shape[0]
    for i in range(n):
        for j in range(n):
            cov_out[r, i, j] = 0.5 * (P[i, j] + P[j, i])
    ok = _finite_pd(cov_out[r], L, n) and np.isfinite(ny)
    for i in range(n):
        if not np.isfinite(mean_out[r, i]):
            ok = False
    return ok


@njit(**_JIT)
def update_kernel(mean, cov, z, measured, R_c, r_scale, thr, use_gate, vis_points, weights, geometry, camera, out):
    """UKF measurement update of R runs (estimator's step around filtering/ukf.update), one run at a time: the
    corners that reach the gate, sigma points, the measurement model's moments, the innovation, the gate, the
    accepted components, the gain and the posterior, the shadow switch (the helpers above, in this order).

    mean (R, 12), cov (R, 12, 12) the prior; z (R, K, m); measured (R, K) bool; R_c (R, K, m, m) per-corner
    covariance, scaled by r_scale (R,); thr (R,) chi-square bound per corner (inf: gate open), used when
    use_gate; vis_points: the visibility check, drop measured corners that the first vis_points sigma points hide
    (0: no check; 1: the mean alone; 2n + 1: the mean and every sigma point; the box face test: K = 8 box
    corners). weights: (Wm, Wc, scale) of the sigma points; geometry: (corners_T (K, 3), face_n (6, 3), face_h
    (6,), face_corners (6, K) bool; the face arrays are read only with vis_points > 0); camera:
    (R_K_from_C, pos_C_m, f, cu, cv, min_depth) for the pixel kinds and kind (0 markers3d, 1 pixels, 2
    pixels+range) last. out: (mean_out, cov_out, nis (R,), accepted and mask_k (R, K) (corners used; corners
    that reached the gate), Ky (R, 12) = K y, yy (R,) = y.y, trPzz (R,) = tr(Pzz) over the used components, ok
    (R,) False where the numpy filter must redo the run), written.
    """
    Wm, Wc, scale = weights
    corners_T, face_n, face_h, face_corners = geometry
    cam_R, cam_pos, cam_f, cam_cu, cam_cv, min_depth, kind = camera
    mean_out, cov_out, nis, accepted, mask_k, Ky, yy, trPzz, ok = out
    R, n = mean.shape
    S = 2 * n + 1
    nc, mdim = z.shape[1], z.shape[2]
    Mx = nc * mdim
    A = np.empty((n, n))
    L = np.empty((n, n))
    sig = np.empty((S, n))
    G = np.empty((3, 3))
    X = np.empty(n * _SP)       # sigma points as columns (flat, see _SP)
    Gs = np.empty((9, _SP))     # Gamma(p) of each sigma point, row-major entries
    zbuf = np.empty(Mx * S)     # z of the sigma points as rows (M, S), then dz
    Wb = np.empty((Mx + n) * S)  # [Wc-weighted dz (M, S); Wc-weighted dx (n, S)]: one BLAS product for both
    zp = np.empty(Mx)
    zsb = np.empty(S * Mx)
    al3 = np.empty((3, _SP))
    Cbuf = np.empty((Mx + n) * Mx)  # [Pzz (M, M); Pxz (n, M)]
    Vtb = np.empty(n * Mx)
    Sm = np.empty((Mx, Mx))
    Ls = np.empty((Mx, Mx))
    Vb = np.empty(Mx * n)
    u = np.empty(Mx)
    y = np.empty(Mx)
    comp = np.empty(Mx, dtype=np.int64)   # compact component -> (corner, axis) index into the 8m vector
    act = np.empty(nc, dtype=np.int64)
    seen = np.empty(nc, dtype=np.bool_)
    buf = np.empty(3)
    Sc = np.empty((3, 3))
    Lc = np.empty((3, 3))
    P = np.empty((n, n))
    Sj = np.empty((3, 3))
    for r in range(R):
        ok[r] = True
        na = _measured_corners(measured, r, mask_k, accepted, act)
        _keep_prior(mean, cov, r, mean_out, cov_out, Ky)
        nis[r], yy[r], trPzz[r] = 0.0, 0.0, 0.0
        if na > 0:
            if not _sigma_points(mean[r], cov[r], scale, A, L, sig):
                ok[r] = False
                continue
            if vis_points > 0:
                na = _shown_by_prior(sig, vis_points, act, na, face_n, face_h, face_corners, G, seen, mask_k, r)
        if na == 0:
            # no update: the numpy filter's update with an empty mask leaves a mean on |p| <= 1 and a
            # positive-definite covariance as they are (otherwise it switches or repairs them: its job)
            ok[r] = _unchanged_ok(mean[r], cov[r], L, P, n)
            continue
        M = na * mdim
        C = Cbuf[:(M + n) * M].reshape((M + n, M))
        for a in range(na):
            for d in range(mdim):
                comp[a * mdim + d] = act[a] * mdim + d
        _to_cols(sig, X)
        zs = zsb[:S * M].reshape((S, M))
        Wv = Wb[:(M + n) * S].reshape((M + n, S))
        _predicted_moments(X, mean, r, act, na, mdim, Wm, Wc, kind, corners_T, cam_R, cam_pos, cam_f, cam_cu,
                           cam_cv, min_depth, Gs, al3, zbuf[:M * S].reshape((M, S)), zs, zp, Wv)
        np.dot(Wv, zs, C)                                          # [Pzz; Pxz] (BLAS)
        _innovation(z, R_c, r, r_scale[r], act, na, mdim, zp, C[:M], y, Sm)
        keep = _gate(Sm, y, na, mdim, thr[r], use_gate, comp, act, accepted, r, Sc, Lc, buf)
        if keep < 0:
            ok[r] = False
            continue
        if keep == 0:
            ok[r] = _unchanged_ok(mean[r], cov[r], L, P, n)  # every measured corner rejected: no update
            continue
        Mk = keep * mdim
        V = Vb[:Mk * n].reshape((Mk, n))
        tr = _compact(keep, na, mdim, n, act, comp, y, Sm, C[:M], C[M:], u, Ls, V)
        if not _chol_lower(Sm, Ls, Mk):
            ok[r] = False
            continue
        ny, yty = _whiten(Ls, y, Mk, n, u, V)
        Vt = Vtb[:n * Mk].reshape((n, Mk))
        _gain_terms(V, u, Mk, r, Ky, Vt)
        np.dot(Vt, V, P)                                           # K S K^T = V^T V (BLAS)
        _posterior(mean, cov, r, Ky, mean_out, P)
        nis[r], yy[r], trPzz[r] = ny, yty, tr
        _shadow_switch(mean_out, r, P, Sj)
        ok[r] = _symmetrized_ok(P, cov_out, mean_out, r, ny, L)


@njit(**_JIT)
def _unchanged_ok(mean, cov, L, P, n):
    """A run left as it is by an update without measurements: its MRP on |p| <= 1 and cov positive definite."""
    pp = mean[_P0] * mean[_P0] + mean[_P0 + 1] * mean[_P0 + 1] + mean[_P0 + 2] * mean[_P0 + 2]
    for i in range(n):
        if not np.isfinite(mean[i]):
            return False
        for j in range(n):
            P[i, j] = cov[i, j]
            if P[i, j] != cov[j, i]:
                return False
    return pp <= 1.0 and _finite_pd(P, L, n)


@njit(**_JIT)
def act_corner(comp, a, mdim):
    """The corner of compact measured-corner slot a (comp holds 8m-vector indices per component)."""
    return comp[a * mdim] // mdim


# ---------------------------------------------------------------- the steps, as filtering/ukf.py's

@njit(**_JIT)
def _chaser_stages(c0, dt, mu, n_sub, stages):
    """filtering.dynamics.chaser_stages over n_sub sub-steps of dt s, the same operations: stages (n_sub, 4, 4)
    the chaser (r_m, rdot_m_s, theta_rad, thetadot_rad_s) at the four RK4 stages of each sub-step."""
    c = c0.copy()
    k = np.empty((4, 4))
    for i in range(n_sub):
        for q in range(4):
            if q == 0:
                cq = c
            else:
                f = dt if q == 3 else 0.5 * dt
                cq = stages[i, q]
                for j in range(4):
                    cq[j] = c[j] + f * k[q - 1, j]
            if q == 0:
                for j in range(4):
                    stages[i, 0, j] = c[j]
            r, rd, thd = cq[0], cq[1], cq[3]
            k[q, 0] = rd
            k[q, 1] = r * _sq(thd) - mu / _sq(r)
            k[q, 2] = thd
            k[q, 3] = -2.0 * rd * thd / r
        for j in range(4):
            c[j] = c[j] + dt / 6.0 * (k[0, j] + 2.0 * k[1, j] + 2.0 * k[2, j] + k[3, j])


_CONSTANTS: dict = {}


def _constants(setup):
    """The kernels' fixed arrays of a FilterSetup, made once: (J, J^-1, keypoints (K, 3), face normals, offsets,
    face membership (of ENVISAT's box: read by the kernel's face test only, which runs for a setup without a
    visibility table), camera rotation, camera position, f, cu, cv, kind code). Keyed by the setup's objects, which
    the cache keeps alive, so an id is never reused while its entry exists."""
    key = (id(setup.J_T), id(setup.camera), id(setup.keypoints_T_m), setup.kind)
    hit = _CONSTANTS.get(key)
    if hit is not None and hit[0] is setup.J_T and hit[1] is setup.camera and hit[2] is setup.keypoints_T_m:
        return hit[3]

    g, cam = load_geometry(), setup.camera
    J = np.ascontiguousarray(setup.J_T, dtype=float)
    c = lambda a, t=float: np.ascontiguousarray(a, dtype=t)  # noqa: E731
    consts = (J, np.linalg.inv(J), c(setup.keypoints_T_m), c(g.face_normals_T), c(g.face_offsets_m),
              c(g.face_corners, bool), c(cam.R_K_from_C), c(cam.pos_C_m), float(cam.f_px), float(cam.cu_px),
              float(cam.cv_px), KIND_CODES[setup.kind])
    if len(_CONSTANTS) > 16:
        _CONSTANTS.clear()
    _CONSTANTS[key] = (setup.J_T, setup.camera, setup.keypoints_T_m, consts)
    return consts


def predict_fused(mean: np.ndarray, cov: np.ndarray, c0: np.ndarray, dt_s: float, Q: np.ndarray, setup,
                  max_step_s: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """filtering.ukf.predict in the fused kernel, with the model of setup (a FilterSetup: inertia, mu, gravity
    gradient, weights). mean (R, 12), cov (R, 12, 12), c0 (4,) the chaser at the start, Q (12, 12) or
    (R, 12, 12) the step's process noise. Returns (mean, cov)."""
    mean = np.ascontiguousarray(mean, dtype=float)
    cov = np.ascontiguousarray(cov, dtype=float)
    R = mean.shape[0]
    Q = np.ascontiguousarray(np.broadcast_to(Q, (R, N_STATE, N_STATE)), dtype=float)
    c = np.ascontiguousarray(c0, dtype=float)
    w, mu, gg = setup.weights, float(setup.mu_m3_s2), bool(setup.gravity_gradient)
    if c.shape != (4,):
        return ukf.predict(mean, cov, c, dt_s, Q, w, setup.J_T, mu, max_step_s, gg)
    n_sub = max(1, int(np.ceil(dt_s / max_step_s - 1e-9)))
    h = dt_s / n_sub
    stages = np.empty((n_sub, 4, 4))
    _chaser_stages(c, h, mu, n_sub, stages)
    J, Jinv = _constants(setup)[:2]
    mean_out, cov_out, ok = np.empty_like(mean), np.empty_like(cov), np.empty(R, dtype=bool)
    predict_kernel(mean, cov, Q, stages, h, w.Wm, w.Wc, float(w.n + w.lam), J, Jinv, mu, gg, mean_out, cov_out, ok)
    if not ok.all():  # covariance repairs: the numpy filter's, on those runs
        bad = ~ok
        mean_out[bad], cov_out[bad] = ukf.predict(mean[bad], cov[bad], c, dt_s, Q[bad], w, setup.J_T, mu,
                                                  max_step_s, gg)
    return mean_out, cov_out


def update_fused(mean: np.ndarray, cov: np.ndarray, z: np.ndarray, measured: np.ndarray, R_c: np.ndarray,
                 r_scale: np.ndarray, thr: np.ndarray | None, vis_check: bool, setup) -> dict:
    """The estimator's measurement update (visibility check, gate, filtering.ukf.update) in the fused kernel.

    mean (R, 12), cov (R, 12, 12) the prior; z (R, K, m); measured (R, K) bool (finite); R_c (R, K, m, m)
    per-corner covariance, used as R_c * r_scale (R,); thr (R,) gate bound per run (inf: open) or None (no
    gate); setup: the estimator's FilterSetup (kind, camera, weights, keypoints, visibility rule: ENVISAT's face
    test runs in the kernel, a target's table is looked up here first). Returns a dict of mean, cov, nis, dof,
    accepted (R, K), mask_k (R, K) (the corners the gate saw), Ky (R, 12) = K y, yy (R,) = y.y, trPzz (R,),
    indefinite (R,) bool (the innovation covariance was not positive definite: the update failed), suspect (k,) the runs the numpy filter redid (the only ones whose results may be non-finite)."""

    mean = np.ascontiguousarray(mean, dtype=float)
    cov = np.ascontiguousarray(cov, dtype=float)
    R = mean.shape[0]
    measured = np.ascontiguousarray(measured, dtype=bool)
    kernel_vis = bool(vis_check) and setup.visibility is None  # the box face test, in the kernel
    if vis_check and not kernel_vis:  # a target's table: the corners the prior hides never reach the kernel
        pts = mean if setup.cfg.visibility_from == "mean" else ukf.sigma_points(mean, cov, setup.weights)
        shown = table_visible(pts, setup.visibility)
        measured = np.ascontiguousarray(measured & (shown if pts is mean else shown.any(axis=-2)), dtype=bool)
    vis_points = (1 if setup.cfg.visibility_from == "mean" else 2 * N_STATE + 1) if kernel_vis else 0
    K = measured.shape[1]
    z = np.ascontiguousarray(z, dtype=float)  # the kernel reads measured corners only (a NaN elsewhere is fine)
    m = z.shape[-1]
    R_c = np.ascontiguousarray(np.broadcast_to(R_c, z.shape + (m,)), dtype=float)
    r_scale = np.ascontiguousarray(r_scale, dtype=float)
    use_gate = thr is not None
    thr_a = np.ascontiguousarray(np.broadcast_to(np.inf if thr is None else thr, (R,)), dtype=float)
    J, Jinv, corners, fn, fh, fc, cR, cpos, f, cu, cv, kind = _constants(setup)
    w = setup.weights
    out = {"mean": np.empty_like(mean), "cov": np.empty_like(cov), "nis": np.empty(R), "yy": np.empty(R),
           "trPzz": np.empty(R), "Ky": np.empty((R, N_STATE)), "accepted": np.empty((R, K), dtype=bool),
           "mask_k": np.empty((R, K), dtype=bool)}
    ok = np.empty(R, dtype=bool)
    out["suspect"] = np.zeros(0, dtype=np.int64)  # runs the numpy filter redid (the kernel's are finite)
    out["indefinite"] = np.zeros(R, dtype=bool)  # runs whose innovation covariance was not positive definite
    update_kernel(mean, cov, z, measured, R_c, r_scale, thr_a, use_gate, vis_points,
                  (w.Wm, w.Wc, float(w.n + w.lam)), (corners, fn, fh, fc),
                  (cR, cpos, f, cu, cv, float(MIN_DEPTH_M), kind),
                  (out["mean"], out["cov"], out["nis"], out["accepted"], out["mask_k"], out["Ky"], out["yy"],
                   out["trPzz"], ok))
    if not ok.all():  # repairs and non-finite steps: the numpy filter's, on those runs
        bad = np.flatnonzero(~ok)
        out["suspect"] = bad
        mk = measured[bad]
        if kernel_vis:
            mk = mk & setup.visible_by_prior(mean[bad], cov[bad])
        Rk = R_c[bad] * r_scale[bad, None, None, None]
        mb, cb, info = ukf.update(mean[bad], cov[bad], z[bad], mk, Rk, setup.hx, w,
                                  None if thr is None else thr_a[bad])
        out["mean"][bad], out["cov"][bad], out["nis"][bad] = mb, cb, info.nis
        out["accepted"][bad], out["mask_k"][bad] = info.accepted, mk
        out["Ky"][bad] = np.einsum("rij,rj->ri", info.K, info.y)
        out["yy"][bad] = np.einsum("ri,ri->r", info.y, info.y)
        out["trPzz"][bad] = np.einsum("rii->r", info.Pzz_state)
        out["indefinite"][bad] = info.indefinite
    out["dof"] = out["accepted"].sum(-1) * m
    return out
