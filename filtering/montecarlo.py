"""Monte Carlo inputs for the filter: per-run measurements of a truth trajectory and initial estimates.

Runs share one truth trajectory and differ in their initial estimate error (drawn from P0) and in their
measurement noise and failures. Run r draws everything from its own Generator, made from
`numpy.random.SeedSequence(seed).spawn(R)[r]`, in a fixed order: initial error, measurement noise, failures.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from envisat_pose.config import check
from envisat_pose.filtering.measurements import (Camera, add_noise, corner_cov, in_frame, limit_markers, measure, outage_mask,
                                    random_failures)


@dataclass(frozen=True)
class MeasurementConfig:
    """What the filter measures and how badly.

    kind: markers3d (corners in C, m), pixels (px), pixels+range (px, px, m).
    sigma_m: 3D corner noise per axis, m. sigma_px: pixel noise per axis, px. sigma_range_m: range noise, m.
    max_markers: at most this many corners per step (the first visible ones in A..H order); 8 = all visible.
    failure_prob: each visible corner is independently lost with this probability at each step.
    outages_s: windows [start, end) in s with no measurement at all (eclipse).
    rate_hz: filter and measurement rate; the truth's sample step must divide 1 / rate_hz.
    f_px, cu_px, cv_px, width_px, height_px: the chaser camera's pinhole intrinsics.
    """

    kind: Literal["markers3d", "pixels", "pixels+range"] = "markers3d"
    sigma_m: float = 0.02
    sigma_px: float = 1.0
    sigma_range_m: float = 0.05
    max_markers: int = 8
    failure_prob: float = 0.0
    outages_s: tuple[tuple[float, float], ...] = ()
    rate_hz: float = 1.0
    f_px: float = 1910.8
    cu_px: float = 511.5
    cv_px: float = 511.5
    width_px: int = 1024
    height_px: int = 1024

    def validate(self, prefix: str = "measurement") -> None:
        p = f"{prefix}." if prefix else ""
        check(self.sigma_m > 0, f"{p}sigma_m", self.sigma_m, "a positive noise sigma in metres")
        check(self.sigma_px > 0, f"{p}sigma_px", self.sigma_px, "a positive noise sigma in pixels")
        check(self.sigma_range_m > 0, f"{p}sigma_range_m", self.sigma_range_m, "a positive noise sigma in metres")
        check(1 <= self.max_markers <= 8, f"{p}max_markers", self.max_markers, "an integer from 1 to 8")
        check(0.0 <= self.failure_prob < 1.0, f"{p}failure_prob", self.failure_prob, "a probability in [0, 1)")
        for i, (a, b) in enumerate(self.outages_s):
            check(0.0 <= a < b, f"{p}outages_s[{i}]", [a, b], "a window [start, end) with 0 <= start < end, s")
        check(0.0 < self.rate_hz <= 100.0, f"{p}rate_hz", self.rate_hz, "a rate in (0, 100] Hz")
        check(self.f_px > 0, f"{p}f_px", self.f_px, "a positive focal length in pixels")
        check(self.width_px > 0 and self.height_px > 0, f"{p}width_px", self.width_px, "a positive image size")

    @property
    def camera(self) -> Camera:
        return Camera(self.f_px, self.cu_px, self.cv_px, self.width_px, self.height_px)

    @property
    def corner_cov(self) -> np.ndarray:
        """Per-corner noise covariance (m, m) of the configured kind."""
        return corner_cov(self.kind, self.sigma_m, self.sigma_px, self.sigma_range_m)


def filter_stride(t_s: np.ndarray, rate_hz: float) -> int:
    """How many truth samples make one filter step; raises ValueError if 1 / rate_hz is not a multiple."""
    dt_truth = float(t_s[1] - t_s[0]) if len(t_s) > 1 else 1.0 / rate_hz
    k = (1.0 / rate_hz) / dt_truth
    if abs(k - round(k)) > 1e-6 or round(k) < 1:
        raise ValueError(f"the filter period 1/rate_hz = {1.0 / rate_hz:g} s is not a multiple of the truth's "
                         f"sample step {dt_truth:g} s")
    return int(round(k))


@dataclass
class RunInputs:
    """Inputs of R runs over T filter steps: x0_hat (R, 12), z (R, T, 8, m), mask (R, T, 8), R_c (m, m)."""

    x0_hat: np.ndarray
    z: np.ndarray
    mask: np.ndarray
    R_c: np.ndarray


def make_run_inputs(x_true: np.ndarray, t_s: np.ndarray, visible: np.ndarray, mcfg: MeasurementConfig,
                    P0: np.ndarray, seed: int, n_runs: int) -> RunInputs:
    """Measurements and initial estimates of n_runs runs of one truth.

    x_true (T, 12) and visible (T, 8) on the filter's time grid t_s (T,). The measured set is the visible
    corners (exact face test), in the image for camera kinds, minus outages and random failures, then limited
    to max_markers.
    """
    cam = mcfg.camera
    z_true = measure(x_true, mcfg.kind, cam)
    base = np.asarray(visible, dtype=bool) & ~outage_mask(t_s, mcfg.outages_s)[:, None]
    if mcfg.kind != "markers3d":
        base &= in_frame(x_true, cam)
    L0 = np.linalg.cholesky(P0)
    cov = mcfg.corner_cov
    x0, zs, masks = [], [], []
    for child in np.random.SeedSequence(seed).spawn(n_runs):
        rng = np.random.default_rng(child)
        x0.append(x_true[0] + L0 @ rng.standard_normal(12))
        zs.append(add_noise(z_true, cov, rng))
        masks.append(limit_markers(random_failures(base, mcfg.failure_prob, rng), mcfg.max_markers))
    return RunInputs(np.stack(x0), np.stack(zs), np.stack(masks), cov)

