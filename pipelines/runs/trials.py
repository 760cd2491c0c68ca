"""Randomized closed-loop trials for the benchmarks (bench/tracking.py, bench/acquisition.py): a lit sun, a random
attitude and tumble axis, each drawn from an explicit generator, and the truth of a trial.

A sun is *lit* for a trial when, on every frame, the chaser is out of the Earth's cylindrical shadow and the sun's
phase angle (between the direction to the sun and the direction from the target to the camera) is at most
phase_max_deg: the camera looks at a sunlit side. The sun is fixed in the inertial frame N; it turns in the LVLH
frame C by the orbit's rate (~0.06 deg/s), so a long run narrows the lit directions. draw_lit_sun_N draws uniformly
on the sphere and keeps the first lit draw: uniform over the lit suns.
"""

from __future__ import annotations

import numpy as np

from envisat_pose.attitude import quat_to_mrp
from envisat_pose.datagen.orbit import chaser_orbit
from envisat_pose.datagen.scenario import in_earth_shadow, scenario_config, scenario_eclipse

# the most phase angle of a lit view, deg: side light at worst (the training views' sun lies within 100 deg,
# datagen/factory.py's sun_phase_max_deg)
SUN_PHASE_MAX_DEG = 90.0
# spawn key of a run seed's sun draw (SeedSequence(seed, spawn_key=(SUN_STREAM,))): apart from the closed loop's
# keys (run,) and (run, 1, k) for any run below 2^20, and from the truth's SeedSequence(seed)
SUN_STREAM = 1 << 20
MAX_SUN_DRAWS = 100_000


def sun_rng(seed: int) -> np.random.Generator:
    """The generator of run seed `seed`'s sun."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(SUN_STREAM,)))


def unit_vector(rng: np.random.Generator) -> np.ndarray:
    """(3,) uniform on the unit sphere."""
    v = rng.standard_normal(3)
    return v / np.linalg.norm(v)


def random_attitude_mrp(rng: np.random.Generator) -> np.ndarray:
    """(3,) an MRP uniform on SO(3) (a normalised 4D Gaussian quaternion, the shadow set with |p| <= 1)."""

    return quat_to_mrp(rng.standard_normal(4))


def phase_angles_deg(sun_N: np.ndarray, R_N_from_C: np.ndarray, rho_C_m: np.ndarray) -> np.ndarray:
    """(T,) the sun's phase angle, deg, per frame: sun_N (3,) unit, R_N_from_C (T, 3, 3), rho_C_m (3,) or (T, 3)
    the target from the chaser in C (the camera looks along it)."""
    sun_C = np.einsum("tji,j->ti", R_N_from_C, sun_N)
    to_camera = -np.broadcast_to(rho_C_m, sun_C.shape)
    cos = np.einsum("ti,ti->t", sun_C, to_camera) / np.linalg.norm(to_camera, axis=-1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def is_lit(sun_N: np.ndarray, orbit, rho_C_m: np.ndarray, phase_max_deg: float) -> bool:
    """Whether sun_N (3,) lights every frame of a chaser orbit (datagen.orbit.ChaserOrbit at the frames' times)
    looking along rho_C_m (3,) or (T, 3): phase within phase_max_deg and out of the Earth's shadow."""

    return bool((phase_angles_deg(sun_N, orbit.R_N_from_C, rho_C_m) <= phase_max_deg).all()
                and not in_earth_shadow(orbit.r_N_m, sun_N).any())


def draw_lit_sun_N(orbit_cfg, t_s: np.ndarray, rho_C_m, rng: np.random.Generator,
                   phase_max_deg: float = SUN_PHASE_MAX_DEG) -> tuple[float, float, float]:
    """A sun direction in N (unit) uniform over those lighting every frame t_s (s) of the chaser's orbit (datagen's
    OrbitConfig) as seen along rho_C_m (the hold's line of sight, m, in C). ValueError when none is found."""

    orbit = chaser_orbit(orbit_cfg, np.asarray(t_s, dtype=float))
    for _ in range(MAX_SUN_DRAWS):
        sun = unit_vector(rng)
        if is_lit(sun, orbit, np.asarray(rho_C_m, dtype=float), phase_max_deg):
            return tuple(round(float(v), 9) for v in sun)
    raise ValueError(f"no sun lights all of {t_s[-1] - t_s[0]:g} s within a {phase_max_deg:g} deg phase angle "
                     f"in {MAX_SUN_DRAWS} draws")


def scenario_sun_N(scenario: str, duration_s: float, rate_hz: float, seed: int,
                   phase_max_deg: float = SUN_PHASE_MAX_DEG) -> tuple[float, float, float] | None:
    """Run seed `seed`'s lit sun for a named scenario's hold over [0, duration_s] at rate_hz (sun_rng); None for a
    scenario whose sun is part of its definition (an [eclipse] table: its shadow is the case studied)."""

    if scenario_eclipse(scenario) is not None:
        return None
    scen = scenario_config(scenario)
    t_s = np.arange(int(np.floor(duration_s * rate_hz + 1e-9)) + 1) / rate_hz
    return draw_lit_sun_N(scen.orbit, t_s, scen.relative.rho0_C_m, sun_rng(seed), phase_max_deg)


def trial_truth_config(scenario: str, duration_s: float, rate_hz: float, seed: int, range_m: float,
                       spin_axis_T, p0_mrp):
    """The truth (datagen's ScenarioConfig) of an acquisition trial: a named scenario's orbit and tumble period,
    the chaser held range_m ahead on V-bar, the tumble about spin_axis_T (3,) from attitude p0_mrp (3,), sampled
    at rate_hz over [0, duration_s]; validated (the keep-out is checked when it is simulated)."""

    return scenario_config(scenario, duration_s=float(duration_s), dt_s=1.0 / rate_hz, seed=int(seed),
                           relative={"rho0_C_m": [0.0, float(range_m), 0.0], "rhodot0_C_m_s": [0.0, 0.0, 0.0]},
                           target={"spin_axis_T": [float(v) for v in spin_axis_T],
                                   "p0_mrp": [float(v) for v in p0_mrp]})
