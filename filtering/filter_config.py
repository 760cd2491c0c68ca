"""The UKF's settings (FilterConfig) and the names its fields choose from; filtering/estimator.py runs the filter
they set."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from envisat_pose.config import Config, check
from envisat_pose.gates import GATE_PROB

KERNELS = ("fast", "reference")  # FilterConfig.kernel: filtering/fast.py's kernels, filtering/ukf.py's numpy
SIGMA_CHARTS = ("additive", "rotation", "screw")  # FilterConfig.sigma_chart (filtering/ukf.py: CHART_MAPS)
VISIBILITY_FROM = ("spread", "mean")  # FilterConfig.visibility_from
# The sigmas a filter or its measurements take (FilterConfig's p0_sigma and q_sigma, MeasurementConfig's noise, the
# tracker's detector_q_sigma): far beyond any physical noise either way, inside where their squares and the
# filter's matrices stay finite and positive (a noise of 1e200 m overflowed its square, one of 1e-300 m made R
# singular, a P0 of 1e100 made the prior singular: each a traceback after the truth was simulated).
SIGMA_MAX = 1e12
SIGMA_MIN = 1e-12  # a positive sigma's least (q_sigma may also be 0: no process noise)
# The unscented transform's centre weights W0 = 1 - 12 / (alpha^2 (12 + kappa)) (mean) and W0 + 1 - alpha^2 + beta
# (covariance): the weighted sums cancel terms |W0| times their result, so |W0| <= 1e8 keeps half of a double's 16
# digits (alpha = 1e-300 divided by 0; beta = 1e300 made the update's matrix singular: tracebacks).
MAX_CENTRE_WEIGHT = 1e8
# Q's factor while a run gets no measurement: at most the ratio of the widest process-noise variance the filter takes
# to the least, (SIGMA_MAX / SIGMA_MIN)^2, so that q_sigma's largest (1e12) inflated is a variance of 1e72 per s
# whose square stays finite (1e300 made the covariance inf: NaN estimates, a warning at most).
MAX_OUTAGE_Q_SCALE = (SIGMA_MAX / SIGMA_MIN) ** 2
# The sigma points lie alpha sqrt(12 + kappa) standard deviations out (3.5 at the defaults): at 100 (kappa = 1e4)
# an estimate on the default truth claimed a mean NEES of 1916 for 12, at 1e150 (kappa = 1e300) its sums were NaN.
MAX_SIGMA_SPREAD = 100.0
# The least RK4 sub-step of the filter's model, s (the truth's least physics step, datagen.scenario's: RK4 at 0.05 s
# is already exact to 1e-8 m over an orbit); a step of 1e-300 s asked for an array past numpy's largest.
MIN_RK4_STEP_S = 1e-4
# The NEES window's steps, and a run's most partial updates: each is an array's length per block of runs, held through
# the run (a window of 1e12 steps or split_max = 1e12 asked numpy for TiBs: a traceback after the truth was made). A
# window of 1e5 steps spans 1000 s at 100 Hz (a window longer than a run is shortened to it); 1024 updates of ratio
# (1 + split_gain) each take any ratio a double holds, (1 + gain)^1024 > 2^1024 overflows.
MAX_DIVERGENCE_WINDOW = 100_000
MAX_SPLIT = 1024


def check_kernel(kernel: str) -> None:
    """ValueError unless kernel is one of KERNELS (the verbs and setups check it before any work)."""
    if kernel not in KERNELS:
        raise ValueError(f"unknown filter kernel {kernel!r}; expected one of {KERNELS} (fast: the fused numba "
                         "kernels, reference: the numpy filter)")


@dataclass(frozen=True)
class FilterConfig(Config):
    """UKF settings. Sigmas are 1-sigma per component; q_* are per second of propagation (Q = q^2 dt).

    p0_sigma: initial uncertainty of (rho m, rho' m/s, p MRP, w_r rad/s), the reference sheet's P0.
    q_sigma: process noise std per sqrt(s) of the same four groups.
    gate_prob: chi-square gate probability per corner (0 switches gating off).
    visibility_check: drop a measured corner that the prior says is hidden (ENVISAT's exact face test, another
    target's fast visibility table): a detection of a hidden corner is a mislabel.
    visibility_from: what says hidden: "spread", the prior's mean and every one of its sigma points (a corner is
    dropped only where the prior's whole spread hides it), or "mean", the prior mean alone, which drops corners in
    view where the mean is off, their measurements then never correcting it (3 markers on a target that does not
    tumble: one run of 20 sat 12 cm off claiming 0.8 cm). The tracker keeps "mean" (TRACKER_FILTER): its detector's
    names of hidden keypoints are mislabels, which a wide acquisition prior's spread would let through.
    gate_lockout_steps: after this many consecutive steps in which the gate rejected every measured corner of a
    run (or, before the run's gate ever accepted most of its corners, most of them and a pose's worth:
    FilterState.locked), its next update is not gated (a filter must not lock itself out when it is wrong or R
    too small); a run released before it was ever confirmed also starts that update from its prior covariance
    plus P0 (wrong from its start, its covariance was too small for its error: the update from it alone
    overshot; a confirmed run is not inflated, where R told too small would make every release a new start).
    adaptive_r / adaptive_q: innovation-based R scale, residual-based Q (see the module docstring).
    outage_q_scale: Q multiplier while a run gets no measurement.
    divergence_window: steps in the NIS window; divergence_prob: false-alarm probability of one window;
    nees_divergence_factor: with a known truth, a window mean NEES above this x 12 also flags divergence.
    divergence_settle_steps: the monitors are armed after this many steps, from step max(settle, window - 1)
    (0-based; the NIS window's and the NEES window's alike) (the initial transient, where P0's
    10 deg attitude uncertainty makes the unscented transform optimistic, is not a divergence).
    The default q_sigma suits a torque-free truth; with the gravity-gradient torque raise the w_r term
    (~1e-5 rad/s^2 at most) or switch on adaptive_q.
    kernel: "fast" (the fused numba kernels of filtering/fast.py, the default) or "reference" (the numpy
    filter of filtering/ukf.py, which the fast one is tested against): the same filter to round-off.
    split_gain, split_max: a run whose prior spreads the measured components more than split_gain times wider
    than their noise takes its measurement in partial updates (filtering/step_update.py), at most split_max
    (1: always one update), their shares of the information growing geometrically, so that every partial
    update's prior is the same few times wider than its noise (step_update.split_factors).
    sigma_chart: "additive" (mean + column), "rotation" (filtering.ukf.chart_retract: the attitude composed, the
    rate turned with it) or "screw" (filtering.screw_chart.screw_retract: besides, the position and velocity errors
    a twist in the body, so a turn about any body line is straight, not only about one through the centre of mass:
    two markers on a line that misses it); the numpy filter runs the last two.
    """

    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0
    p0_sigma: tuple[float, float, float, float] = (1.0, 0.01, 0.044, 1.7e-3)
    q_sigma: tuple[float, float, float, float] = (1e-7, 1e-7, 1e-8, 1e-9)
    gate_prob: float = GATE_PROB
    gate_lockout_steps: int = 5
    visibility_check: bool = True
    visibility_from: str = "spread"
    adaptive_r: bool = False
    adaptive_r_rate: float = 0.05
    adaptive_r_bounds: tuple[float, float] = (0.2, 100.0)
    adaptive_q: bool = False
    adaptive_q_memory: float = 0.95
    outage_q_scale: float = 10.0
    divergence_window: int = 30
    divergence_settle_steps: int = 60
    nees_divergence_factor: float = 10.0
    divergence_prob: float = 1e-6
    max_rk4_step_s: float = 1.0
    kernel: str = "fast"
    split_gain: float = 10.0
    split_max: int = 16
    sigma_chart: str = "additive"

    def validate(self, prefix: str = "filter") -> None:
        p = f"{prefix}." if prefix else ""
        check(0.0 < self.alpha <= 1.0, f"{p}alpha", self.alpha, "a sigma-point spread in (0, 1]")
        check(self.beta >= 0.0, f"{p}beta", self.beta, "a non-negative number")
        check(12 + self.kappa > 0, f"{p}kappa", self.kappa, "a number with 12 + kappa > 0")
        self._check_unscented(p)
        check(all(SIGMA_MIN <= s <= SIGMA_MAX for s in self.p0_sigma), f"{p}p0_sigma", list(self.p0_sigma),
              f"four positive sigmas in [{SIGMA_MIN:g}, {SIGMA_MAX:g}]")
        check(all(s == 0 or SIGMA_MIN <= s <= SIGMA_MAX for s in self.q_sigma), f"{p}q_sigma", list(self.q_sigma),
              f"four sigmas, each 0 or in [{SIGMA_MIN:g}, {SIGMA_MAX:g}]")
        check(0.0 <= self.gate_prob < 1.0, f"{p}gate_prob", self.gate_prob, "a probability in [0, 1) (0: no gate)")
        check(self.gate_lockout_steps >= 1, f"{p}gate_lockout_steps", self.gate_lockout_steps, "at least 1 step")
        check(0.0 < self.adaptive_r_rate <= 1.0, f"{p}adaptive_r_rate", self.adaptive_r_rate, "a rate in (0, 1]")
        lo, hi = self.adaptive_r_bounds
        check(0.0 < lo <= 1.0 <= hi, f"{p}adaptive_r_bounds", list(self.adaptive_r_bounds), "[lo, hi] with 0 < lo <= 1 <= hi")
        check(0.0 <= self.adaptive_q_memory < 1.0, f"{p}adaptive_q_memory", self.adaptive_q_memory, "a number in [0, 1)")
        check(1.0 <= self.outage_q_scale <= MAX_OUTAGE_Q_SCALE, f"{p}outage_q_scale", self.outage_q_scale,
              f"a factor in [1, {MAX_OUTAGE_Q_SCALE:g}] (the widest ratio of the process noises the filter takes)")
        check(self.divergence_settle_steps >= 0, f"{p}divergence_settle_steps", self.divergence_settle_steps, "a non-negative number of steps")
        check(1 <= self.divergence_window <= MAX_DIVERGENCE_WINDOW, f"{p}divergence_window", self.divergence_window,
              f"1 to {MAX_DIVERGENCE_WINDOW} steps")
        check(0.0 < self.divergence_prob < 1.0, f"{p}divergence_prob", self.divergence_prob, "a probability in (0, 1)")
        check(self.nees_divergence_factor > 1.0, f"{p}nees_divergence_factor", self.nees_divergence_factor, "a factor > 1")
        check(self.max_rk4_step_s >= MIN_RK4_STEP_S, f"{p}max_rk4_step_s", self.max_rk4_step_s,
              f"a step of at least {MIN_RK4_STEP_S:g} s (RK4 is exact at 0.05 s; smaller steps only cost time)")
        check(self.kernel in KERNELS, f"{p}kernel", self.kernel, f"one of {', '.join(KERNELS)}")
        check(self.split_gain > 1.0, f"{p}split_gain", self.split_gain, "a factor > 1")
        check(1 <= self.split_max <= MAX_SPLIT, f"{p}split_max", self.split_max, f"1 to {MAX_SPLIT} updates (1024 "
              "take any ratio a double holds)")
        check(self.visibility_from in VISIBILITY_FROM, f"{p}visibility_from", self.visibility_from,
              " or ".join(VISIBILITY_FROM))
        check(self.sigma_chart in SIGMA_CHARTS, f"{p}sigma_chart", self.sigma_chart, " or ".join(SIGMA_CHARTS))

    def _check_unscented(self, p: str) -> None:
        """ConfigError unless the sigma points' weights and spread stay where the unscented transform's sums are
        sound (MAX_CENTRE_WEIGHT, MAX_SIGMA_SPREAD)."""
        scaled = self.alpha ** 2 * (12 + self.kappa)  # n + lambda
        spread = scaled ** 0.5
        check(spread <= MAX_SIGMA_SPREAD, f"{p}kappa", self.kappa, f"sigma points at most {MAX_SIGMA_SPREAD:g} "
              f"standard deviations out: alpha sqrt(12 + kappa) = {spread:.3g}")
        w0 = 1.0 - 12.0 / scaled if scaled > 0 else -math.inf
        check(abs(w0) <= MAX_CENTRE_WEIGHT, f"{p}alpha", self.alpha, f"a centre weight 1 - 12 / (alpha^2 (12 + "
              f"kappa)) within +-{MAX_CENTRE_WEIGHT:g} (kappa = {self.kappa:g}): a larger one cancels the sums' digits")
        w0_cov = w0 + 1.0 - self.alpha ** 2 + self.beta
        check(abs(w0_cov) <= MAX_CENTRE_WEIGHT, f"{p}beta", self.beta, f"a covariance centre weight W0 + 1 - alpha^2 "
              f"+ beta within +-{MAX_CENTRE_WEIGHT:g} (it is {w0_cov:.3g}): a larger one cancels the sums' digits")

    @property
    def P0(self) -> np.ndarray:
        """Initial covariance (12, 12)."""
        return np.diag(np.repeat(np.square(self.p0_sigma), 3))

    def Q(self, dt_s: float) -> np.ndarray:
        """Process noise of a step of dt_s seconds (12, 12)."""
        return np.diag(np.repeat(np.square(self.q_sigma), 3)) * dt_s
