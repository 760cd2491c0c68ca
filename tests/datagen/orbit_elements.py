"""Textbook two-body helpers the datagen tests share as their independent reference (not the code under test)."""

import math

import numpy as np
from scipy.spatial.transform import Rotation

MU = 3.986004418e14  # the Earth's gravitational parameter, m^3/s^2 (the reference sheet's)


def elements_to_rv(a, e, i_deg, raan_deg, argp_deg, nu_deg):
    """Textbook perifocal -> inertial conversion (3-1-3 rotation by RAAN, inclination, argument of perigee)."""
    nu = math.radians(nu_deg)
    p = a * (1 - e**2)
    r_pf = p / (1 + e * math.cos(nu)) * np.array([math.cos(nu), math.sin(nu), 0.0])
    v_pf = math.sqrt(MU / p) * np.array([-math.sin(nu), e + math.cos(nu), 0.0])
    R = Rotation.from_euler("ZXZ", [raan_deg, i_deg, argp_deg], degrees=True).as_matrix()
    return R @ r_pf, R @ v_pf
