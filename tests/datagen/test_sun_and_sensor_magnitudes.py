"""The sun of sequence frames and the space camera's magnitudes, against computations of the test's own.

Sun: the chaser's orbit solved here from the reference sheet's elements (Kepler's equation by scipy's brentq, the
perifocal frame turned by scipy's Rotation, LVLH from r and v), the sun's direction carried into C and the camera
frame K by hand, the Earth's cylindrical shadow (reference.md section 2, scenario.EclipseConfig) tested on points
placed on either side of its boundary and crossed by root finding; rendered frames checked face by face against
the lambert rule (a face turned away from the sun gets no sunlight) with the attitude from the reference sheet's
Gamma(p).

Camera: images built here as plain arrays (a point, a bar, a ramp); the streak's extent, the point spread's second
moment, the Airy pattern's first dark ring, the saturation level and the exposure's gain measured on the output and
compared with the magnitudes the docstrings promise (sensor.py, corrupt.py, camera_response.py), the sRGB curve
written out from IEC 61966-2-1.
"""

import math
import os
from types import SimpleNamespace

os.environ.setdefault("MUJOCO_GL", "osmesa")

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from envisat_pose.config import from_dict, to_dict
from envisat_pose.datagen import sensor
from envisat_pose.datagen.corrupt import apply_corruption, draw_corruption, no_corruption
from envisat_pose.datagen.generate_config import GenerateConfig, SensorConfig, config_json
from envisat_pose.datagen.scenario import (
    EclipseConfig,
    eclipse_windows,
    in_earth_shadow,
    scenario_config,
    scenario_eclipse,
)
from envisat_pose.datagen.views import sequence_frames, sequence_view

# ---------------------------------------------------------------------------------------------------------
# The orbit by hand (reference.md section 2: the default orbit)

MU = 398600.4418e9  # m^3/s^2
A_M, ECC, INC_DEG, RAAN_DEG, ARGP_DEG, NU0_DEG = 7142.0e3, 0.001, 98.4, 0.0, 90.0, 30.0
MEAN_MOTION = math.sqrt(MU / A_M**3)  # 1.046018e-3 rad/s
PERIOD_S = 2.0 * math.pi / MEAN_MOTION  # 100.11 min
R_EARTH_M = 6378137.0  # WGS-84 equatorial radius: the "one Earth radius" of the shadow cylinder
# The camera mount of reference.md section 6 / models/envisat.xml: boresight +y_C, image up +x_C; rows are the
# camera axes (x right, y down, z boresight) in C: x_K = -z_C, y_K = -x_C, z_K = +y_C.
R_K_FROM_C = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def orbit_by_hand(t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(r_N (3,) m, R_N_from_C (3, 3), columns the LVLH axes in N) of the default orbit at t_s: Kepler's equation
    solved by brentq, the perifocal state turned by Rz(raan) Rx(i) Rz(argp); x = r / |r|, z = h / |h|, y = z x x."""
    nu0 = math.radians(NU0_DEG)
    E0 = 2.0 * math.atan(math.sqrt((1.0 - ECC) / (1.0 + ECC)) * math.tan(nu0 / 2.0))
    M = E0 - ECC * math.sin(E0) + MEAN_MOTION * t_s
    E = brentq(lambda E: E - ECC * math.sin(E) - M, M - 1.0, M + 1.0, xtol=1e-15)
    nu = 2.0 * math.atan2(math.sqrt(1.0 + ECC) * math.sin(E / 2.0), math.sqrt(1.0 - ECC) * math.cos(E / 2.0))
    p = A_M * (1.0 - ECC**2)
    r = p / (1.0 + ECC * math.cos(nu))
    r_P = r * np.array([math.cos(nu), math.sin(nu), 0.0])
    v_P = math.sqrt(MU / p) * np.array([-math.sin(nu), ECC + math.cos(nu), 0.0])
    Q = Rotation.from_euler("ZXZ", [RAAN_DEG, INC_DEG, ARGP_DEG], degrees=True).as_matrix()
    r_N, v_N = Q @ r_P, Q @ v_P
    x, z = unit(r_N), unit(np.cross(r_N, v_N))
    return r_N, np.stack([x, np.cross(z, x), z], axis=1)


def shadow_by_hand(r_N, sun_N) -> bool:
    """reference.md section 2 / EclipseConfig: behind the Earth (r . s < 0), within one Earth radius of the sun line."""
    s = unit(sun_N)
    along = float(r_N @ s)
    return along < 0.0 and float(np.linalg.norm(r_N - along * s)) < R_EARTH_M


def gamma_by_hand(p) -> np.ndarray:
    """reference.md section 4: Gamma(p) = I - a1 [p x] + a2 [p x]^2 (C components to T components)."""
    p = np.asarray(p, dtype=float)
    px = np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])
    s = float(p @ p)
    return np.eye(3) - 4.0 * (1.0 - s) / (1.0 + s) ** 2 * px + 8.0 / (1.0 + s) ** 2 * px @ px


# the sun of the sequence tests: at t = 0 from behind the chaser (mostly -y_C, the camera looks along +y_C); the
# LVLH frame turns once per orbit about z_C, so a quarter orbit later the sun is behind the Earth (-x_C mostly:
# in the shadow) and half an orbit later behind the target. Given in N with a length of 3.7 (any length is allowed).
SUN_C_AT_0 = unit([0.25, -1.0, 0.35])
SUN_N = 3.7 * (orbit_by_hand(0.0)[1] @ SUN_C_AT_0)
FRAME_DT_S = PERIOD_S / 4.0


@pytest.fixture(scope="module")
def sequence_cfg():
    cfg = from_dict(GenerateConfig, {"mode": "sequence", "num_images": 3, "resolution_px": 192,
                                     "sun_dir": SUN_N.tolist(), "earth_probability": 0.0,
                                     "sequence": {"scenario": "default", "frame_dt_s": FRAME_DT_S}})
    o = scenario_config("default").orbit  # the sequence flies the default scenario: the sheet's orbit
    assert (o.a_m, o.e, o.i_deg, o.raan_deg, o.argp_deg, o.nu0_deg) == (A_M, ECC, INC_DEG, RAAN_DEG, ARGP_DEG, NU0_DEG)
    assert o.mu_m3_s2 == MU
    return cfg


def test_sequence_sun_is_the_inertial_sun_turned_through_the_orbit_into_c_and_the_camera(sequence_cfg):
    """At t = 0, a quarter and half an orbit: the frames' sun in C is R_N_from_C^T s_N / |s_N| of the orbit solved
    here, the label's sun_dir_cam that turned into K by the camera mount, the eclipse flag the shadow's own rule,
    and the View the renderer gets carries that sun, or none in the shadow."""
    t_s, _, sun_C, eclipse, nadir_C = sequence_frames(config_json(sequence_cfg))
    np.testing.assert_allclose(t_s, np.arange(3) * FRAME_DT_S, rtol=0, atol=1e-9)
    expect_dark = []
    for k, t in enumerate(t_s):
        r_N, R_N_from_C = orbit_by_hand(float(t))
        s_C = R_N_from_C.T @ unit(SUN_N)
        # two double-precision Kepler solutions of the same orbit agree to ~1e-12 rad; a transposed rotation, a
        # wrong time or a mirrored axis are O(1) errors
        np.testing.assert_allclose(sun_C[k], s_C, rtol=0, atol=1e-9)
        # the Earth's centre is at -r x_C, r = |r_N| (1e-3 m: 1e-16 relative of 7e6 m, rounding)
        np.testing.assert_allclose(nadir_C[k], [-np.linalg.norm(r_N), 0.0, 0.0], rtol=0, atol=1e-3)
        dark = shadow_by_hand(r_N, SUN_N)
        expect_dark.append(dark)
        assert bool(eclipse[k]) == dark
        view, _, scene = sequence_view(sequence_cfg, k)
        # the scene's sun_dir_cam is rounded to 9 decimals (views.sequence_view): 1e-8
        np.testing.assert_allclose(scene["sun_dir_cam"], R_K_FROM_C @ s_C, rtol=0, atol=1e-8)
        assert scene["eclipse"] is dark
        if dark:
            assert view.sun_dir_C is None
        else:
            np.testing.assert_allclose(view.sun_dir_C, s_C, rtol=0, atol=1e-9)
    # the chosen sun does what the test says of it: lit, in the shadow, lit; front-lit, then back-lit
    assert expect_dark == [False, True, False]
    assert sun_C[0][1] < -0.8 and sun_C[2][1] > 0.8 and sun_C[1][0] < -0.8


def test_a_point_is_in_the_shadow_exactly_inside_the_night_side_cylinder():
    """Points 1 km either side of the cylinder's wall (one Earth radius from the sun line), on the night side and
    mirrored onto the day side, near the terminator plane and far behind; the sun given at any length."""
    s_raw = np.array([2.0, -1.0, 0.5])
    s = unit(s_raw)
    e1 = unit(np.cross(s, [0.0, 0.0, 1.0]))
    e2 = np.cross(s, e1)
    pts, expect = [], []
    for behind_m in (1.0e3, 7.0e6, 4.0e8):  # near the terminator plane, a low orbit's distance, the Moon's
        for phi in np.radians([0.0, 77.0, 200.0]):
            wall = math.cos(phi) * e1 + math.sin(phi) * e2
            for off_m, dark in ((-1.0e3, True), (1.0e3, False)):  # 1 km: far beyond rounding at 1e7 m
                pts.append(-behind_m * s + (R_EARTH_M + off_m) * wall)
                expect.append(dark)
                pts.append(+behind_m * s + (R_EARTH_M + off_m) * wall)  # the day side: never dark
                expect.append(False)
    pts.append(-7.0e6 * s)  # on the axis behind the Earth
    expect.append(True)
    pts.append(1.0 * s + 0.5 * R_EARTH_M * e1)  # 1 m on the sun's side of the terminator plane: lit
    expect.append(False)
    pts.append(-1.0 * s + 0.5 * R_EARTH_M * e1)  # 1 m behind it: dark
    expect.append(True)
    pts = np.array(pts)
    assert [shadow_by_hand(p, s_raw) for p in pts] == expect  # the test's points sit where it says
    assert in_earth_shadow(pts, s_raw).tolist() == expect
    assert in_earth_shadow(pts, 1e-3 * s_raw).tolist() == expect


@pytest.mark.parametrize("case", ["eclipse scenario", "beta 40 deg"])
def test_eclipse_windows_open_and_close_where_the_orbit_crosses_the_shadow_wall(case):
    """The scenario's shadow windows against the crossings of the cylinder's wall found here by root finding on
    the orbit solved here: a window starts at the first output sample in the shadow and ends at the first one out."""
    if case == "eclipse scenario":
        eclipse = scenario_eclipse("eclipse")
        cfg = scenario_config("eclipse", duration_s=PERIOD_S, dt_s=5.0)
    else:  # a sun 40 deg out of the orbit plane: a shorter shadow, its wall crossed off the plane of the orbit
        _, R0 = orbit_by_hand(0.0)
        sun = math.cos(math.radians(40.0)) * R0[:, 1] + math.sin(math.radians(40.0)) * R0[:, 2]
        eclipse = EclipseConfig(tuple(sun.tolist()))
        cfg = scenario_config("default", duration_s=PERIOD_S, dt_s=5.0)
    sun = np.asarray(eclipse.sun_dir_N, dtype=float)
    grid = np.arange(0.0, PERIOD_S, 10.0)
    dark = np.array([shadow_by_hand(orbit_by_hand(t)[0], sun) for t in grid])

    def wall(t):  # distance from the sun line minus one Earth radius, on the night side of the crossing
        r = orbit_by_hand(t)[0]
        return float(np.linalg.norm(r - (r @ unit(sun)) * unit(sun))) - R_EARTH_M

    flips = np.flatnonzero(dark[1:] != dark[:-1])
    crossings = [brentq(wall, grid[i], grid[i + 1], xtol=1e-6) for i in flips]
    assert len(crossings) == 2 and dark[flips[0] + 1] and not dark[flips[1] + 1]  # one pass, inside the orbit
    t_in, t_out = crossings
    (start, end), = eclipse_windows(cfg, eclipse)
    # the window's edges are output samples (dt_s = 5 s): the first inside and the first outside
    assert t_in <= start < t_in + 5.0, (start, t_in)
    assert t_out <= end < t_out + 5.0, (end, t_out)
    if case == "eclipse scenario":  # its file: in the shadow from ~600 s to ~2700 s
        assert 550.0 < start < 650.0 and 2650.0 < end < 2760.0


# ---------------------------------------------------------------------------------------------------------
# The sequence frames rendered

FACE_NORMALS_T = {1: (1, 0, 0), 2: (-1, 0, 0), 3: (0, 1, 0), 4: (0, -1, 0), 5: (0, 0, 1), 6: (0, 0, -1)}


@pytest.fixture(scope="module")
def renderer():
    from envisat_pose.datagen.render import SceneRenderer

    r = SceneRenderer(192, shadows=False, earth_texture_set_size=0)  # no shadow map: a face is lit by n . s alone
    yield r
    r.close()


def test_rendered_sequence_frames_are_lit_from_the_orbits_sun_and_dark_in_the_shadow(sequence_cfg, renderer):
    """Frames 0 and 2 (sun behind the chaser, then behind the target): every visible face turned away from the sun
    (n . s < 0, n from the truth's MRP through Gamma, s from the orbit solved here) is dark and every face facing it
    squarely is lit; frame 1, in the shadow, is labelled so, has no sun in its render record and renders dark
    through the factory's own view (its appearance and light draws)."""
    from envisat_pose.datagen.factory import sample_view

    t_s, x, _, _, _ = sequence_frames(config_json(sequence_cfg))
    lit_faces = {}
    for k in (0, 2):
        view, xk, _ = sequence_view(sequence_cfg, k)
        out = renderer.render(view)
        s_C = orbit_by_hand(float(t_s[k]))[1].T @ unit(SUN_N)
        R_C_from_T = gamma_by_hand(xk[6:9]).T
        lit_faces[k] = []
        for value, n_T in FACE_NORMALS_T.items():
            face = out.mask_u8 == value
            if face.sum() < 40:  # a face seen edge-on: too few pixels for a median
                continue
            cos_sun = float((R_C_from_T @ np.array(n_T, float)) @ s_C)
            level = float(np.median(out.gray_u8[face]))
            # unlit: the headlight's ambient 0.02 of the brightest material (foil, 0.78) is ~4 grey levels; lit at
            # n . s > 0.3: the sun's 1.2 x 0.3 on the darkest panel (0.16) is ~15 grey levels, more with specular
            if cos_sun < -0.05:
                assert level <= 6, (k, value, cos_sun, level)
            elif cos_sun > 0.3:
                assert level >= 10, (k, value, cos_sun, level)
                lit_faces[k].append(value)
    assert lit_faces[0], "front-lit frame: some visible face faces the sun"
    assert not lit_faces[2], "back-lit frame: no visible face faces the sun"
    # the shadow frame through the factory's path: labelled in eclipse, no sun recorded, rendered without sunlight
    _, _, _, view, xk, scene = sample_view(sequence_cfg, 0, 1, 30.0, 0.1, None)
    assert scene["eclipse"] is True and scene["render"]["sun_dir_C"] is None and view.sun_dir_C is None
    assert scene["earthshine"]["intensity"] == 0.0  # no Earth-shine from the night side
    out = renderer.render(view)
    body = out.mask_u8 > 0
    assert body.sum() > 500
    assert out.gray_u8[body].max() <= 8  # the ambient alone (as above); a sunlit face reaches tens to hundreds


# ---------------------------------------------------------------------------------------------------------
# The space camera: images as plain arrays, magnitudes measured on the output

F_PX_1024 = 1910.8  # reference.md section 6: 30 deg over 1024 px


def sensor_cfg(**ranges) -> dict:
    """[corruption.sensor] as a dict with degenerate ranges: one camera, no vignetting, a PSF well below a pixel."""
    cfg = to_dict(SensorConfig())
    cfg.update(psf="gaussian", psf_sigma_px_1024=[0.3, 0.3], vignetting_cos_power=[0.0, 0.0])
    cfg.update({k: list(v) if isinstance(v, tuple) else v for k, v in ranges.items()})
    return cfg


def quiet(p: dict, **kw) -> dict:
    """No read noise, dark current or PRNU (each tested on its own elsewhere): a mean is the light's alone."""
    return {**p, "read_noise_e": 0.0, "dark_current_e_per_s": 0.0, "prnu_sigma": 0.0, **kw}


def half_max_width(profile: np.ndarray) -> float:
    """Width of a plateaued profile between its two half-plateau crossings (linear interpolation), px."""
    prof = np.asarray(profile, dtype=float)
    plateau = np.median(prof[prof > 0.5 * prof.max()])
    half = 0.5 * plateau
    above = np.flatnonzero(prof > half)
    i0, i1 = above[0], above[-1]
    left = i0 - 1 + (half - prof[i0 - 1]) / (prof[i0] - prof[i0 - 1])
    right = i1 + (prof[i1] - half) / (prof[i1] - prof[i1 + 1])
    return float(right - left)


def moments(img: np.ndarray) -> tuple[float, float, float]:
    """(var_x, var_y, cov_xy) of an image's light, px^2."""
    img = np.asarray(img, dtype=np.float64)
    ys, xs = np.indices(img.shape)
    m = img.sum()
    mx, my = (img * xs).sum() / m, (img * ys).sum() / m
    return ((img * (xs - mx) ** 2).sum() / m, (img * (ys - my) ** 2).sum() / m,
            (img * (xs - mx) * (ys - my)).sum() / m)


def point_image(side: int = 96) -> np.ndarray:
    img = np.zeros((side, side), np.uint8)
    img[side // 2, side // 2] = 255
    return img


@pytest.mark.parametrize("motion", ["translation", "tumble"])
def test_motion_streak_is_angular_rate_times_exposure_times_focal_length(motion):
    """A point-like target (a 1 cm cluster) 40 m out: moving across the line of sight at v (angular rate v / z), or
    a point 5 m in front of the centre of a target turning at 5 deg/s about the image's x axis (w d / (z - d)).
    The factory's image motion (from the truth state: rho' in C, w_r in T, any attitude) and the drawn exposure
    make a streak of rate x exposure x f px; a single lit pixel through the optics spreads over that many pixels
    along x (translation) or y (tumble), and no wider across."""
    from envisat_pose.datagen.factory import image_motion

    exposure_s, z_m = 0.5, 40.0
    R_K_from_T = Rotation.from_rotvec([0.4, -1.1, 0.7]).as_matrix()  # any attitude
    x = np.zeros(12)
    if motion == "translation":
        v_C = np.array([0.0, 0.0, 0.4])  # along z_C = -x_K: across the image's rows
        x[3:6] = v_C
        pts_K = np.array([[0.01, 0, 0], [-0.01, 0, 0], [0, 0.01, 0], [0, -0.01, 0]])
        rate_rad_s, along_x = float(np.linalg.norm(v_C)) / z_m, True
    else:
        w, d = math.radians(5.0), 5.0
        x[9:12] = R_K_from_T.T @ np.array([w, 0.0, 0.0])  # w_r is in T
        pts_K = np.array([[0.0, 0.0, -d]])  # on the boresight, d toward the camera: moves along y_K at w d
        rate_rad_s, along_x = w * d / (z_m - d), False
    t_K = np.array([0.0, 0.0, z_m])
    out = SimpleNamespace(R_K_from_T=R_K_from_T, t_K_from_T_m=t_K)
    boxes = SimpleNamespace(corners_T_m=pts_K @ R_K_from_T)  # K -> T: R_K_from_T^T p, row-wise
    speed, angle = image_motion(out, x, F_PX_1024, boxes)
    p = sensor.draw_sensor(sensor_cfg(exposure_s=(exposure_s, exposure_s)), 1024, F_PX_1024, speed, angle,
                           np.random.default_rng(0))
    length = rate_rad_s * exposure_s * F_PX_1024  # ~19 px (translation), ~21 px (tumble)
    # the parameter: exact up to the 6 decimals draw_sensor keeps
    assert abs(p["motion_blur_length_px"] - length) < 1e-5
    assert (min(angle, 180.0 - angle) if along_x else abs(angle - 90.0)) < 1e-6  # x: 0 (mod 180), y: 90 deg
    img = sensor.optics(point_image(), p)
    along, across = (img.sum(axis=0), img.sum(axis=1)) if along_x else (img.sum(axis=1), img.sum(axis=0))
    # the streak's extent: the line is sampled every ~1/4 px with full-weight end samples (+1/4 px), splatted
    # bilinearly and its half-plateau points interpolated (+-0.1 px): 0.5 px; a 10 % error is 2 px
    assert abs(half_max_width(along) - length) < 0.5, (half_max_width(along), length)
    var_across = moments(img)[0 if not along_x else 1]
    assert var_across < 0.2  # across: the 0.3 px PSF alone (sigma^2 + 1/12 = 0.17 px^2)
    assert across.argmax() == 48 and across[48] > 0.9


def test_the_whole_camera_chain_keeps_the_streaks_length():
    """The same streak through every step (electrons, shot noise, full well, ADC): a single pixel bright enough
    (white 15 x the full well) to fill the streak's ~20 px to ~3/4 of the well, read from the 8-bit output."""
    length = 20.0
    p = sensor.draw_sensor(sensor_cfg(exposure_s=(0.01, 0.01), full_well_e=(1e5, 1e5), white_fill=(15.0, 15.0),
                                      adc_bits=(12,)), 1024, F_PX_1024, length / 0.01, 0.0, np.random.default_rng(1))
    assert p["motion_blur_length_px"] == length
    # 1 e-/s of dark current (0.01 e- in the exposure): see the test below for why not 0
    img = sensor.apply_sensor(point_image(), quiet(p, dark_current_e_per_s=1.0)).astype(float)
    row = img[48]
    # plateau 15/20 of the well: ~190 grey levels, shot noise 270 e- = 0.7 grey levels: the half-plateau points
    # move by < 0.05 px; with the kernel's own 0.35 px (above): 0.5 px
    assert 170 < np.median(row[row > 100]) < 205
    assert abs(half_max_width(row) - length) < 0.5, half_max_width(row)
    assert img[40:47].max() == 0 and img[50:57].max() == 0  # no streak across the motion


def test_a_camera_without_dark_current_images_a_long_streak():
    """dark_current_e_per_s = 0 is a valid range (SensorConfig.validate: [0, 1e6]); a 20 px streak of a bright
    patch must still give an image (the irradiance is light: never below 0). cv2.filter2D's DFT path (kernels of
    11 px and more) left -2e-16 where it was dark, which shot noise then read as a negative mean (ValueError)."""
    cfg = sensor_cfg(dark_current_e_per_s=(0.0, 0.0), exposure_s=(0.01, 0.01))
    p = sensor.draw_sensor(cfg, 1024, F_PX_1024, 20.0 / 0.01, 30.0, np.random.default_rng(7))
    img = np.zeros((96, 96), np.uint8)
    img[30:60, 40:56] = 200
    out = sensor.apply_sensor(img, p)
    assert out.shape == img.shape and out[45, 48] > 0


@pytest.mark.parametrize("length", [6.0, 15.0])
def test_paper_motion_blur_streak_is_its_configured_length(length):
    """'paper' model: motion_blur_length_px is the streak's length in px (here a vertical bright bar smeared along
    x); the severities' lengths are at 1024 px and halve at 512 px."""
    params = no_corruption() | {"levels": {**no_corruption()["levels"], "motion_blur": "low"},
                                "motion_blur_length_px": length, "motion_blur_angle_deg": 0.0}
    img = np.zeros((64, 96), np.uint8)
    img[16:48, 48] = 255
    out = apply_corruption(img, params).astype(float)
    # 8-bit rounding of a plateau of 255 / length (17 to 43 grey levels) moves the crossings by < 0.1 px; with the
    # kernel's own 0.35 px (test above): 0.5 px
    assert abs(half_max_width(out[16:48].mean(axis=0)) - length) < 0.5
    sev = {"exposure": "none", "motion_blur": "high", "gaussian_blur": "high", "shot_noise": "none",
           "gaussian_noise": "none"}
    a = draw_corruption(sev, 1024, np.random.default_rng(3))
    b = draw_corruption(sev, 512, np.random.default_rng(3))
    assert b["motion_blur_length_px"] == pytest.approx(a["motion_blur_length_px"] / 2, rel=1e-6)
    assert b["gaussian_blur_sigma_px"] == pytest.approx(a["gaussian_blur_sigma_px"] / 2, rel=1e-6)


@pytest.mark.parametrize("adc_bits", [8, 10, 12])
def test_the_white_level_saturates_at_full_well_and_is_linear_below(adc_bits):
    """A ramp of grey levels 0..255 across the columns, white = 2 x the full well: a column whose light fills the
    well (grey >= 127.5) reads the top of the ADC, shown as 255, in every pixel (whatever the bit depth); below, the
    8-bit value is 255 x charge / full well = 2 x grey, and nothing clips early."""
    fw = 20000.0
    p = sensor.draw_sensor(sensor_cfg(full_well_e=(fw, fw), white_fill=(2.0, 2.0), adc_bits=(adc_bits,)), 256,
                           1.0, 0.0, 0.0, np.random.default_rng(2))
    assert p["white_e"] == 2.0 * fw
    grey = np.arange(256)
    img = np.repeat(grey[None, :].astype(np.uint8), 256, axis=0)  # constant columns: blooming stays in them
    out = sensor.apply_sensor(img, quiet(p)).astype(float)
    mean_e = grey / 255.0 * 2.0 * fw
    sd_e = np.sqrt(mean_e)  # shot noise, e-
    full = mean_e - 6.0 * sd_e >= fw  # saturated in every pixel (6 sigma)
    below = mean_e + 6.0 * sd_e < fw
    assert full.sum() > 100 and below.sum() > 100
    assert np.all(out[:, full] == 255)
    expect = 255.0 * mean_e[below] / fw  # 2 x grey
    # per column: 256 pixels of shot noise <= 1.8 grey levels (141 e- at the well) and the rounding: standard
    # error <= 0.12; 0.6 is 5 of them (a 1 % gain error is 2.5 grey levels at the top)
    np.testing.assert_allclose(out[:, below].mean(axis=0), expect, rtol=0, atol=0.6)
    assert out[:, below].max() < 255


def srgb_by_hand(v):
    """IEC 61966-2-1: 12.92 v up to 0.0031308, 1.055 v^(1/2.4) - 0.055 above (v linear light, 0..1)."""
    v = np.asarray(v, dtype=float)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1.0 / 2.4) - 0.055)


def srgb_decode_by_hand(s):
    s = np.asarray(s, dtype=float)
    return np.where(s <= 0.04045, s / 12.92, np.power((s + 0.055) / 1.055, 2.4))


def test_doubling_the_exposure_doubles_the_signal_below_saturation():
    """At a fixed photon flux, white_e = flux x exposure and the dark charge = dark current x exposure
    (sensor.py step 4): twice the exposure gives twice the mean 8-bit value, light and dark charge alike, until
    the well fills; stored through the sRGB response, the stored value is the curve of that linear value, so
    decoding it (by the IEC formula) shows the doubling."""
    fw, flux, dark = 2.0e5, 4.0e6, 2.0e5  # e-, e-/s at white, e-/s
    t1 = 0.01
    p = sensor.draw_sensor(sensor_cfg(full_well_e=(fw, fw), exposure_s=(t1, t1), white_fill=(0.2, 0.2),
                                      adc_bits=(16,)), 256, 1.0, 0.0, 0.0, np.random.default_rng(4))
    assert p["white_e"] == pytest.approx(p["photon_flux_e_per_s_at_white"] * p["exposure_s"], rel=1e-6)
    grey = np.repeat(np.arange(0, 256, 5)[None, :].astype(np.uint8), 200, axis=0)

    def at(t, **kw):
        q = quiet(p, exposure_s=t, white_e=flux * t, dark_current_e_per_s=dark, **kw)
        return sensor.apply_sensor(grey, q).astype(float)

    one, two = at(t1), at(2 * t1)
    e1 = grey[0] / 255.0 * flux * t1 + dark * t1  # electrons at t1: 2000 of dark, up to 40000 of light
    expect1 = 255.0 * e1 / fw
    ok = 2.0 * e1 + 6.0 * np.sqrt(2.0 * e1) < fw  # below the well at twice the exposure
    assert ok.sum() > 30
    # per column: 200 pixels, shot noise <= 0.76 grey levels at t1 (<= 1.1 at 2 t1) and rounding: standard error
    # <= 0.08; 0.4 is 5 of them. A 10 % error in the gain is > 2 grey levels above grey 100.
    np.testing.assert_allclose(one.mean(axis=0), expect1, rtol=0, atol=0.4)
    np.testing.assert_allclose(two.mean(axis=0)[ok], 2.0 * expect1[ok], rtol=0, atol=0.4)
    # through the sRGB curve: each pixel stores round(255 srgb(linear / 255)); decoded by hand, the means double
    s1, s2 = at(t1, response="srgb"), at(2 * t1, response="srgb")
    lin = np.rint(one)  # the same noise seed: the linear frames above, pixel for pixel
    np.testing.assert_array_equal(s1, np.rint(255.0 * srgb_by_hand(lin / 255.0)))
    d1 = 255.0 * srgb_decode_by_hand(s1 / 255.0)
    d2 = 255.0 * srgb_decode_by_hand(s2 / 255.0)
    bright = ok & (expect1 > 20)
    # an 8-bit sRGB code spans up to 2.3 linear grey levels near white: its rounding, averaged over 200 noisy
    # pixels (noise ~1 grey level), leaves < 0.5 level; 2 % of the ratio at 25+ grey levels covers it
    np.testing.assert_allclose(d2.mean(axis=0)[bright] / d1.mean(axis=0)[bright], 2.0, rtol=0.02)
    assert np.all(s2.mean(axis=0)[bright] < 1.9 * s1.mean(axis=0)[bright])  # the stored values do not double


def test_paper_exposure_gain_multiplies_and_clips_at_white():
    """'paper' model: exposure_gain multiplies the clean grey levels, rounded, clipped at 255."""
    params = no_corruption() | {"levels": {**no_corruption()["levels"], "exposure": "high"}, "exposure_gain": 2.0}
    grey = np.arange(256, dtype=np.uint8)[None, :]
    out = apply_corruption(grey, params)[0].astype(int)
    np.testing.assert_array_equal(out, np.minimum(2 * np.arange(256), 255))


@pytest.mark.parametrize("resolution_px, sigma_1024", [(512, 3.0), (1024, 1.6)])
def test_gaussian_psf_spreads_a_point_by_its_configured_sigma(resolution_px, sigma_1024):
    """psf_sigma_px_1024 is the Gaussian's sigma at 1024 px, scaled to the image: a point through the optics spreads
    with variance sigma^2 per axis plus the pixel's integration (1/12 px^2), no covariance."""
    sigma = sigma_1024 * resolution_px / 1024.0
    p = sensor.draw_sensor(sensor_cfg(psf_sigma_px_1024=(sigma_1024, sigma_1024)), resolution_px,
                           F_PX_1024 * resolution_px / 1024, 0.0, 0.0, np.random.default_rng(5))
    assert p["psf"] == {"kind": "gaussian", "sigma_px": sigma}
    vx, vy, cxy = moments(sensor.optics(point_image(), p))
    # 4 x 4 sub-samples integrate the pixel as 5/64 px^2 rather than 1/12 and the kernel stops at 4 sigma + 1 px
    # (3e-4 of the variance): 1 % in sigma
    for v in (vx, vy):
        assert abs(math.sqrt(v - 1.0 / 12.0) - sigma) < 0.01 * sigma, (v, sigma)
    assert abs(cxy) < 1e-6


def test_airy_psf_has_its_first_dark_ring_at_1_22_lambda_n():
    """An Airy PSF's first dark ring at 1.22 lambda N / pixel pitch: the radial profile of a point through the
    optics has its first minimum there (N 32.8 puts it at 4 px at 1024 px, 8 px at 2048 px: the pitch scales)."""
    lam, pitch_1024 = 550e-9, 5.5e-6
    for res, n_f in ((1024, 32.8), (2048, 32.8)):
        cfg = sensor_cfg(psf="airy", f_number=(n_f, n_f), wavelength_m=lam, pixel_pitch_m_1024=pitch_1024)
        p = sensor.draw_sensor(cfg, res, F_PX_1024 * res / 1024, 0.0, 0.0, np.random.default_rng(6))
        r0 = 1.22 * lam * n_f / (pitch_1024 * 1024 / res)
        img = sensor.optics(point_image(128), p).astype(float)
        ys, xs = np.indices(img.shape)
        r = np.hypot(xs - 64, ys - 64)
        ring = (r > 0.5 * r0) & (r < 1.5 * r0)
        darkest = np.argmin(np.where(ring, img, np.inf))
        # the darkest pixel of the annulus lies on the ring: the pixels' radii near r0 are ~0.1-0.2 px apart and
        # the pixel's integration (4 x 4 sub-samples) flattens the zero's bottom: 0.3 px (7 % of r0 at 1024 px);
        # a missing 1.22 or a pitch not scaled with the resolution moves it by a fifth of r0 or more
        assert abs(r.ravel()[darkest] - r0) < 0.3, (res, r.ravel()[darkest], r0)
        assert img.ravel()[darkest] < 0.01 * img.max()  # a dark ring, not a shoulder (the next ring: 1.7 %)


def test_paper_gaussian_blur_spreads_a_point_by_its_sigma():
    """'paper' model: gaussian_blur_sigma_px is the blur's sigma in px (cv2's sampled Gaussian: variance sigma^2
    to 1 %)."""
    for sigma in (1.0, 2.5):
        params = no_corruption() | {"levels": {**no_corruption()["levels"], "gaussian_blur": "low"},
                                    "gaussian_blur_sigma_px": sigma}
        # apply_corruption rounds to 8 bits: a 255 point at sigma 2.5 peaks at 6.5 levels and the rounding cuts
        # the tails; a 5 x 5 block (variance (25 - 1) / 12 = 2 px^2 per axis, subtracted) keeps them above 0.5
        img = np.zeros((96, 96), np.uint8)
        img[46:51, 46:51] = 255
        vx, vy, _ = moments(apply_corruption(img, params))
        for v in (vx, vy):
            # 8-bit rounding of the tails (below 0.5 level beyond ~3.5 sigma) takes ~1 % of the variance: 2 %
            assert abs(math.sqrt(v - 2.0) - sigma) < 0.02 * sigma, (v, sigma)
