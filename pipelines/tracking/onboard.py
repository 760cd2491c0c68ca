"""What the chaser knows on board of the truth it tracks: the physics its filter's model shares with the truth
(onboard_physics: the one builder of it; `envisat estimate`, `montecarlo`, `run` and the benches use it) and
its own orbit (orbit_config, chaser_function)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from envisat_pose.config import InputError
from envisat_pose.datagen.orbit import chaser_orbit
from envisat_pose.datagen.scenario import scenario_of_truth


class OnboardPhysics(NamedTuple):
    """The truth's physics the filter's model must share: mu_m3_s2 (the Earth's gravitational parameter,
    m^3/s^2) and gravity_gradient (the target feels the gravity-gradient torque)."""

    mu_m3_s2: float
    gravity_gradient: bool


def onboard_physics(truth, source: str = "the truth") -> OnboardPhysics:
    """The physics of a truth (a TruthTrajectory, or anything with its config dict) that the filter's model must
    share, read from its config (orbit.mu_m3_s2, target.gravity_gradient); InputError naming `source` if the config
    lacks them or holds something else."""
    try:
        cfg = truth.config
        mu = float(cfg["orbit"]["mu_m3_s2"])
        gg = cfg["target"]["gravity_gradient"]
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(f"{source}: its config_json does not give orbit.mu_m3_s2 and target.gravity_gradient "
                         f"({type(err).__name__}: {err})") from None
    if not (np.isfinite(mu) and mu > 0) or not isinstance(gg, bool):
        raise InputError(f"{source}: its config_json has orbit.mu_m3_s2 = {mu!r} and target.gravity_gradient = "
                         f"{gg!r}; expected a positive number and true/false")
    return OnboardPhysics(mu, gg)


def orbit_config(truth_config: dict):
    """The chaser's Keplerian orbit (datagen's OrbitConfig) of a truth's config."""

    return scenario_of_truth(truth_config).orbit


def chaser_function(orbit):
    """chaser_at(t_s) -> (4,) the chaser's polar orbit (r_m, rdot_m_s, theta_rad, thetadot_rad_s) from its
    Keplerian elements: what the chaser knows of itself on board."""

    def chaser_at(t_s: float) -> np.ndarray:
        o = chaser_orbit(orbit, np.array([float(t_s)]))
        return np.array([o.r_m[0], o.rdot_m_s[0], o.theta_rad[0], o.thetadot_rad_s[0]])

    return chaser_at
