"""Monte Carlo inputs for the filter: per-run measurements of a truth trajectory and initial estimates.

Measurements come from the truth, never from the filter's own model: `truth_measurements` turns the truth's
arrays (MuJoCo's corner sites corners_C_m, their projection corners_px through MuJoCo's camera, the visibility
and in-frame flags) into noise-free measurements z_true (T, K, m) and the measurable set (T, K), K the truth's
keypoints (its target's: ENVISAT's corners A-H, K = 8, or another target file's).
Runs share one truth trajectory and differ in their initial estimate error (drawn from P0) and in their
measurement noise and failures. Run r draws everything from its own Generator, made from
`numpy.random.SeedSequence(seed, spawn_key=(r,))` (the same as `SeedSequence(seed).spawn(R)[r]`), in a fixed
order: initial error, measurement noise, failures. Run r's draws depend on r only, so a block of runs [a, b)
(`first_run=a`) draws exactly what the whole campaign draws for those runs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from envisat_pose.config import Config, check
from envisat_pose.filtering.filter_config import SIGMA_MAX, SIGMA_MIN
from envisat_pose.filtering.measurements import (
    KINDS,
    add_noise,
    corner_cov,
    limit_markers,
    outage_mask,
    random_failures,
)
from envisat_pose.geometry import PinholeCamera, load_camera
from envisat_pose.state import draw_initial_estimate


@dataclass(frozen=True)
class MeasurementConfig(Config):
    """What the filter measures and how badly.

    kind: markers3d (corners in C, m), pixels (px), pixels+range (px, px, m).
    sigma_m: 3D corner noise per axis, m. sigma_px: pixel noise per axis, px. sigma_range_m: range noise, m.
    max_markers: at most this many keypoints per step (the first visible ones in the target's keypoint order, A..H
    for ENVISAT), from 1 to the target's K; None (the default) = all visible.
    failure_prob: each visible corner is independently lost with this probability at each step.
    outages_s: windows [start, end) in s with no measurement at all (eclipse).
    rate_hz: filter and measurement rate; the truth's sample step must divide 1 / rate_hz.
    The camera is the MJCF's (envisat_pose.geometry.load_camera), not a setting.
    """

    kind: Literal["markers3d", "pixels", "pixels+range"] = "markers3d"
    sigma_m: float = 0.02
    sigma_px: float = 1.0
    sigma_range_m: float = 0.05
    max_markers: int | None = None
    failure_prob: float = 0.0
    outages_s: tuple[tuple[float, float], ...] = ()
    rate_hz: float = 1.0

    def validate(self, prefix: str = "measurement") -> None:
        p = f"{prefix}." if prefix else ""
        for name, unit in (("sigma_m", "metres"), ("sigma_px", "pixels"), ("sigma_range_m", "metres")):
            check(SIGMA_MIN <= getattr(self, name) <= SIGMA_MAX, f"{p}{name}", getattr(self, name),
                  f"a positive noise sigma in {unit}, in [{SIGMA_MIN:g}, {SIGMA_MAX:g}]")
        check(self.max_markers is None or self.max_markers >= 1, f"{p}max_markers", self.max_markers,
              "an integer from 1 to the target's number of keypoints (omit it for all)")
        check(0.0 <= self.failure_prob < 1.0, f"{p}failure_prob", self.failure_prob, "a probability in [0, 1)")
        for i, (a, b) in enumerate(self.outages_s):
            check(0.0 <= a < b, f"{p}outages_s[{i}]", [a, b], "a window [start, end) with 0 <= start < end, s")
        check(0.0 < self.rate_hz <= 100.0, f"{p}rate_hz", self.rate_hz, "a rate in (0, 100] Hz")

    def check_keypoints(self, num_keypoints: int, prefix: str = "measurement") -> None:
        """ConfigError unless max_markers fits a target of num_keypoints keypoints (1..K, or None)."""
        p = f"{prefix}." if prefix else ""
        check(self.max_markers is None or 1 <= self.max_markers <= num_keypoints, f"{p}max_markers",
              self.max_markers, f"an integer from 1 to {num_keypoints} (the target's keypoints; omit it for all)")

    @property
    def corner_cov(self) -> np.ndarray:
        """Per-corner noise covariance (m, m) of the configured kind."""
        return corner_cov(self.kind, self.sigma_m, self.sigma_px, self.sigma_range_m)


def filter_stride(t_s: np.ndarray, rate_hz: float) -> int:
    """How many truth samples make one filter step; raises ValueError if 1 / rate_hz is not a multiple."""
    dt_truth = float(t_s[1] - t_s[0]) if len(t_s) > 1 else 1.0 / rate_hz
    k = (1.0 / rate_hz) / dt_truth
    if abs(k - round(k)) > 1e-6 or round(k) < 1:
        raise ValueError(f"a rate whose period 1/rate_hz = {1.0 / rate_hz:g} s is a whole multiple of the truth's "
                         f"sample step {dt_truth:g} s")
    return int(round(k))


@dataclass
class RunInputs:
    """Inputs of R runs over T filter steps: x0_hat (R, 12), z (R, T, K, m), mask (R, T, K), R_c (m, m)."""

    x0_hat: np.ndarray
    z: np.ndarray
    mask: np.ndarray
    R_c: np.ndarray


def truth_measurements(kind: str, corners_C_m: np.ndarray, visible: np.ndarray, corners_px: np.ndarray | None = None,
                       in_frame: np.ndarray | None = None, camera: PinholeCamera | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free measurements of a truth and the corners that can be measured, from the truth's own arrays.

    corners_C_m (T, K, 3) m: the truth's keypoints in C (MuJoCo's sites); visible (T, K) bool; corners_px (T, K, 2)
    px and in_frame (T, K) bool: MuJoCo's projection through its camera (needed by the pixel kinds).
    markers3d: z = corners_C_m, measurable where visible. pixels: z = corners_px, measurable where visible and
    in frame. pixels+range: (corners_px, |corners_C_m - camera centre|), same set. camera: for the range's
    centre (default load_camera()). Returns z_true (T, K, m), base_mask (T, K) bool.
    """
    corners_C_m = np.asarray(corners_C_m, dtype=float)
    visible = np.asarray(visible, dtype=bool)
    if kind == "markers3d":
        return corners_C_m, visible
    if kind not in KINDS:
        raise ValueError(f"unknown measurement kind {kind!r}; expected one of {KINDS}")
    if corners_px is None or in_frame is None:
        raise ValueError(f"measurement kind {kind!r} needs the truth's corners_px and in_frame")
    uv = np.asarray(corners_px, dtype=float)
    base = visible & np.asarray(in_frame, dtype=bool)
    if kind == "pixels":
        return uv, base
    camera = camera or load_camera()
    rng_m = np.linalg.norm(corners_C_m - camera.pos_C_m, axis=-1, keepdims=True)
    return np.concatenate([uv, rng_m], axis=-1), base


def make_run_inputs(x0_true: np.ndarray, t_s: np.ndarray, z_true: np.ndarray, base_mask: np.ndarray,
                    mcfg: MeasurementConfig, P0: np.ndarray, seed: int, n_runs: int, first_run: int = 0,
                    init_error_scale: float = 1.0) -> RunInputs:
    """Measurements and initial estimates of n_runs runs of one truth.

    x0_true (12,): the true state at t_s[0]; t_s (T,) the filter's time grid; z_true (T, K, m) noise-free
    measurements and base_mask (T, K) bool the measurable keypoints on that grid (truth_measurements). The
    measured set is base_mask minus outages and random failures, then limited to max_markers (at most K: a
    ConfigError otherwise). The runs are
    first_run .. first_run + n_runs - 1; run r draws, from SeedSequence(seed, spawn_key=(r,)) (=
    SeedSequence(seed).spawn(R)[r]): its initial error (from N(0, init_error_scale^2 P0): a scale other than 1
    studies a filter told the wrong P0), its noise, its failures.
    """
    z_true = np.asarray(z_true, dtype=float)
    mcfg.check_keypoints(z_true.shape[-2])
    base = np.asarray(base_mask, dtype=bool) & ~outage_mask(np.asarray(t_s), mcfg.outages_s)[:, None]
    cov = mcfg.corner_cov
    if z_true.shape[-1] != cov.shape[-1]:
        raise ValueError(f"z_true has {z_true.shape[-1]} components per corner; kind {mcfg.kind!r} has {cov.shape[-1]}")
    init_cov = float(init_error_scale) ** 2 * np.asarray(P0, dtype=float)
    x0, zs, masks = [], [], []
    for r in range(first_run, first_run + n_runs):
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(r,)))
        x0.append(draw_initial_estimate(x0_true, init_cov, rng))
        zs.append(add_noise(z_true, cov, rng))
        masks.append(limit_markers(random_failures(base, mcfg.failure_prob, rng), mcfg.max_markers))
    return RunInputs(np.stack(x0), np.stack(zs), np.stack(masks), cov)


def inputs_from_truth(truth, mcfg: MeasurementConfig, P0: np.ndarray, seed: int, n_runs: int,
                      sel: slice = slice(None)) -> RunInputs:
    """make_run_inputs from a truth trajectory (envisat_pose.contracts.TruthTrajectory) of any target (its K
    keypoints), sampled at `sel`."""
    z_true, base = truth_measurements(mcfg.kind, truth.corners_C_m[sel], truth.visible[sel],
                                      truth.corners_px[sel], truth.in_frame[sel])
    return make_run_inputs(truth.x[sel][0], truth.t_s[sel], z_true, base, mcfg, P0, seed, n_runs)
