"""The space camera model against closed forms: shot noise variance = mean (electrons), saturation at full well,
blooming conserves charge with its exponential profile, PSFs integrate to 1 (Gaussian second moment, Airy first
dark ring), vignetting is cos^n, the ADC's bit depth, PRNU per camera seed, the motion streak of a known rate."""

import math

import numpy as np
import pytest

from envisat_pose.config import to_dict
from envisat_pose.datagen import sensor
from envisat_pose.datagen.generate_config import SensorConfig


def params(**kw):
    p = sensor.draw_sensor(to_dict(SensorConfig()), 256, 477.7, 0.0, 0.0, np.random.default_rng(0))
    p.update({"read_noise_e": 0.0, "dark_current_e_per_s": 0.0, "prnu_sigma": 0.0, "adc_bits": 12,
              "vignetting_cos_power": 0.0, "motion_blur_length_px": 0.0, "psf": {"kind": "gaussian", "sigma_px": 0.3}})
    p.update(kw)
    return p


@pytest.mark.parametrize("mean_e", [3.0, 40.0, 5000.0])
def test_shot_noise_variance_equals_mean(mean_e):
    x = sensor.shot_noise_e(np.full((400, 500), mean_e, np.float32), np.random.default_rng(1))
    n = x.size
    assert abs(x.mean() - mean_e) < 5 * math.sqrt(mean_e / n)
    # variance of the sample variance of a Poisson: ~ 2 mean^2 / n (plus mean / n)
    assert abs(x.var() - mean_e) < 5 * math.sqrt((2 * mean_e**2 + mean_e) / n)
    if mean_e < sensor.POISSON_EXACT_BELOW_E:
        assert np.all(x == np.round(x)) and x.min() >= 0  # whole electrons


def test_saturation_clips_at_full_well_and_bloom_conserves_charge():
    fw, decay = 1000.0, 2.0
    charge = np.zeros((41, 5), np.float32)
    charge[20, 2] = fw + 600.0
    out = sensor.bloom(charge, fw, decay)
    assert out.max() <= fw and out[20, 2] == fw
    assert abs(out.sum() - charge.sum()) < 1e-2  # the spill lands in the column's empty neighbours
    assert np.all(out[:, [0, 1, 3, 4]] == 0)  # only along the column
    d = np.arange(1, 8)
    z = 2 * np.exp(-np.arange(1, int(math.ceil(6 * decay)) + 1) / decay).sum()
    np.testing.assert_allclose(out[20 + d, 2], 600.0 * np.exp(-d / decay) / z, rtol=1e-5)
    np.testing.assert_allclose(out[20 - d, 2], out[20 + d, 2], rtol=1e-6)
    # a hugely over-exposed image: every pixel at full well, shown as white
    p = params(white_e=50 * 20000.0, full_well_e=20000.0, adc_bits=12)
    img = sensor.apply_sensor(np.full((32, 32), 200, np.uint8), p)
    assert np.all(img == 255)


def test_psfs_integrate_to_one_with_their_closed_forms():
    for sigma in (0.5, 1.0, 2.5):
        k = sensor.gaussian_psf(sigma).astype(np.float64)
        assert abs(k.sum() - 1) < 1e-6
        c = np.arange(k.shape[0]) - k.shape[0] // 2
        var = (k.sum(axis=0) * c**2).sum()
        # pixel integration (4 x 4 sub-samples) adds ~1/12 px^2 to sigma^2
        assert abs(var - (sigma**2 + 1 / 12)) < 0.04 * sigma**2 + 0.005, (sigma, var)
    for r0 in (1.0, 2.2):
        k = sensor.airy_psf(r0)
        assert abs(float(k.astype(np.float64).sum()) - 1) < 1e-6
    # the first dark ring at 1.22 lambda N (in pixels), the profile's closed form
    assert sensor.airy_profile(np.array([2.2]), 2.2)[0] < 1e-12
    assert sensor.airy_profile(np.array([0.0]), 2.2)[0] == 1.0
    p = sensor.draw_sensor({**to_dict(SensorConfig()), "psf": "airy"}, 1024, 1910.8, 0, 0, np.random.default_rng(3))
    assert abs(p["psf"]["first_zero_px"] - 1.22 * 550e-9 * p["psf"]["f_number"] / 5.5e-6) < 2e-3


def test_vignetting_is_cos_to_the_n():
    f = 100.0
    v = sensor.vignetting_factor((101, 101), f, 4.0)
    assert v[50, 50] == 1.0
    r = math.hypot(50, 50)
    assert abs(v[0, 0] - math.cos(math.atan(r / f)) ** 4) < 1e-6
    assert np.array_equal(sensor.vignetting_factor((101, 101), f, 4.0, (10, 40, 55, 101)), v[10:40, 55:101])
    img = sensor.optics(np.full((101, 101), 255, np.uint8), params(vignetting_cos_power=4.0, f_px=f,
                                                                   psf={"kind": "gaussian", "sigma_px": 0.05}))
    assert abs(img[0, 50] - math.cos(math.atan(50 / f)) ** 4) < 2e-3


def test_adc_bit_depth_and_read_noise_and_dark_current():
    ramp = np.linspace(0, 1000.0, 4096, dtype=np.float32).reshape(64, 64)
    for bits in (8, 10, 12):
        out = sensor.adc_to_u8(ramp, 1000.0, bits)
        expect = np.rint(np.rint(ramp * (2**bits - 1) / 1000.0) * (255 / (2**bits - 1)))
        assert np.array_equal(out, expect.astype(np.uint8))
    # a black image: electrons = Poisson(dark x exposure) + N(0, read); in 16-bit DN the variance is their sum
    p = params(dark_current_e_per_s=400.0, exposure_s=0.01, read_noise_e=5.0, full_well_e=65535.0, adc_bits=16)
    rng = np.random.default_rng(p["noise_seed"])
    mean_e = np.full((300, 300), 4.0, np.float32)
    charge = sensor.shot_noise_e(mean_e, rng) + 5.0 * rng.standard_normal((300, 300))
    assert abs(charge.mean() - 4.0) < 0.1 and abs(charge.var() - (4.0 + 25.0)) < 1.0


def test_prnu_is_fixed_per_camera():
    a = sensor.prnu_gain(7, (64, 64), 0.01)
    assert np.array_equal(a, sensor.prnu_gain(7, (64, 64), 0.01))
    assert not np.array_equal(a, sensor.prnu_gain(8, (64, 64), 0.01))
    assert abs(a.std() - 0.01) < 0.001 and abs(a.mean() - 1.0) < 0.001
    flat = params(prnu_sigma=0.02, camera_seed=7, white_e=0.5 * 200000.0, full_well_e=200000.0, adc_bits=16)
    # the fixed pattern repeats from image to image of the same camera: two noise seeds, correlated residuals
    one = sensor.apply_sensor(np.full((64, 64), 255, np.uint8), flat).astype(float)
    assert one.std() > 0


def test_motion_streak_of_a_known_rate():
    """A point at 1 m off the centre, rotating about the boresight at w: image speed f w r / z."""
    f, z, w = 1000.0, 50.0, math.radians(3.0)
    pts = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    speed, angle = sensor.image_velocity_px_s(pts, np.eye(3), np.array([0.0, 0.0, z]), np.array([0.0, 0.0, w]),
                                              np.zeros(3), f)
    assert abs(speed - f * w * 1.0 / z) < 1e-9 and abs(angle - 90.0) < 1e-6  # points on x move along y
    # a lateral velocity: f v / z along x
    speed, angle = sensor.image_velocity_px_s(pts, np.eye(3), np.array([0.0, 0.0, z]), np.zeros(3),
                                              np.array([0.5, 0.0, 0.0]), f)
    assert abs(speed - f * 0.5 / z) < 1e-9 and min(angle, 180 - angle) < 1e-6


def test_airy_psf_far_below_a_pixel_is_a_point_not_nan():
    """At 96 px the default optics put the Airy ring at ~0.05 px: no sub-sample meets it; the PSF is a delta
    (it was 0/0 = NaN, and the image's cast to uint8 was garbage)."""
    k = sensor.airy_psf(0.046)
    assert np.isfinite(k).all() and k[k.shape[0] // 2, k.shape[1] // 2] == 1.0 and k.sum() == 1.0
    img = np.zeros((40, 40), np.uint8)
    img[10:30, 12:28] = 200
    p = params(psf={"kind": "airy", "first_zero_px": 0.046}, white_e=0.5 * 20000.0, full_well_e=20000.0)
    with np.errstate(all="raise"):
        out = sensor.apply_sensor(img, p)
    assert abs(out[12:28, 14:26].mean() - 100.0) < 3.0 and out[:8].max() < 10


# --- the fast path: unlit pixels drawn from their exact distribution, lit ones pixel by pixel -------------


def flat_params(**kw):
    """One electron per DN at 8 bits (full well 255 e-), no PRNU, vignetting or motion: the 8-bit value is
    the charge rounded, so its moments have closed forms."""
    return params(full_well_e=255.0, adc_bits=8, white_e=200.0, dark_current_e_per_s=2000.0, exposure_s=0.01,
                  read_noise_e=4.0, blooming_decay_px=2.0, **kw)


def test_pixel_class_moments_match_the_closed_forms():
    """Per pixel class, mean and variance of the 8-bit output: unlit pixels (dark charge lam_d = 20 e-, exact
    Poisson), a patch below POISSON_EXACT_BELOW_E (60 e-: exact Poisson) and one above (170 e-: its Gaussian
    limit): mean = lam, variance = lam (shot) + read^2 + 1/12 (rounding to whole DN)."""
    img = np.zeros((600, 600), np.uint8)
    img[60:280, 60:280] = 51  # 51 / 255 x 200 e- = 40 e- of light + 20 e- dark = 60 e-
    img[320:540, 320:540] = 191  # 150 e- of light (191 / 255 x 200 = 149.8) + 20 e- = 169.8 e-
    p = flat_params()
    read2 = 16.0
    classes = {"unlit": (np.s_[560:600, 0:600], 20.0), "poisson": (np.s_[70:270, 70:270], 20.0 + 200 * 51 / 255),
               "gaussian": (np.s_[330:530, 330:530], 20.0 + 200 * 191 / 255)}
    for seed in (1, 2):
        out = sensor.apply_sensor(img, {**p, "noise_seed": seed}).astype(np.float64)
        for name, (sl, lam) in classes.items():
            x = out[sl].ravel()
            n = x.size
            var = lam + read2 + 1 / 12
            assert abs(x.mean() - lam) < 5 * math.sqrt(var / n), (name, x.mean(), lam)
            assert abs(x.var() - var) < 5 * var * math.sqrt(2 / n), (name, x.var(), var)
        # the unlit pixels far from the content (the table-drawn ones) and the unlit ones inside the box agree
        far, near = out[560:600].ravel(), out[285:315, 60:280].ravel()
        assert abs(far.var() - near.var()) < 5 * 36 * math.sqrt(2 / near.size)


def test_same_seed_same_bytes_and_seeds_differ():
    img = np.zeros((300, 300), np.uint8)
    img[100:200, 80:220] = 180
    img[140:150, 140:150] = 255
    p = params(white_e=30000.0, full_well_e=20000.0, dark_current_e_per_s=300.0, exposure_s=0.01, read_noise_e=6.0,
               adc_bits=10, prnu_sigma=0.01, vignetting_cos_power=4.0, f_px=400.0)
    a, b = sensor.apply_sensor(img, p), sensor.apply_sensor(img, dict(p))
    assert np.array_equal(a, b)
    c = sensor.apply_sensor(img, {**p, "noise_seed": p["noise_seed"] + 1})
    assert not np.array_equal(a, c)
    assert (a[145, 100:200] == 255).all()  # saturated


@pytest.mark.parametrize("dark_e,read_e,bits,full_well", [(4.0, 8.0, 8, 14000.0), (20.0, 4.0, 12, 3000.0),
                                                        (0.5, 0.0, 12, 1000.0), (150.0, 10.0, 10, 2000.0),
                                                        (9.0, 3.0, 16, 65535.0)])
def test_dark_pixel_distribution_against_an_independent_simulation(dark_e, read_e, bits, full_well):
    """dark_pixel_pmf (Poisson or its Gaussian limit, read noise, ADC, 8-bit display, in closed form) against
    the chain simulated directly in float64 (numpy's Poisson and normal): total variation below 0.004."""
    p = params(dark_current_e_per_s=dark_e / 0.01, exposure_s=0.01, read_noise_e=read_e, adc_bits=bits,
               full_well_e=full_well)
    pmf = sensor.dark_pixel_pmf(p)
    rng = np.random.default_rng(5)
    n = 1_000_000
    lam = float(np.float32(dark_e))
    charge = rng.poisson(lam, n).astype(np.float64) if lam < sensor.POISSON_EXACT_BELOW_E else \
        lam + math.sqrt(lam) * rng.standard_normal(n)
    charge += read_e * rng.standard_normal(n)
    top = 2**bits - 1
    dn = np.clip(np.rint(charge * top / full_well), 0, top)
    u8 = np.rint(dn * 255 / top).astype(int) if bits != 8 else dn.astype(int)
    hist = np.bincount(u8, minlength=256) / n
    assert abs(pmf.sum() - 1) < 1e-9
    assert 0.5 * np.abs(hist - pmf).sum() < 0.004
    drawn = np.bincount(sensor.sample_discrete(pmf, n, np.random.default_rng(6)), minlength=256) / n
    assert 0.5 * np.abs(drawn - pmf).sum() < 0.004


def test_sample_discrete_is_exact_in_distribution():
    pmf = np.array([0.5, 0.25 - 1e-4, 1e-4, 0.125, 0.0, 0.125])
    n = 2_000_000
    x = sensor.sample_discrete(pmf, n, np.random.default_rng(0))
    f = np.bincount(x, minlength=6) / n
    assert f[4] == 0
    assert np.all(np.abs(f - pmf) < 5 * np.sqrt(pmf * (1 - pmf) / n) + 1e-9)
    # a distribution with steps in every byte interval: the fallback path does all of it
    pmf = np.full(256, 1 / 256)
    f = np.bincount(sensor.sample_discrete(pmf, n, np.random.default_rng(1)), minlength=256) / n
    assert np.abs(f - pmf).max() < 5 * math.sqrt(pmf[0] / n)


def test_blooming_spills_beyond_the_optics_box():
    """A small saturated spot blooms along its column farther than the optics reach: the spill survives
    the unlit pixels' draw around it, and the column keeps (most of) the charge."""
    img = np.zeros((200, 200), np.uint8)
    img[98:102, 99:101] = 255
    p = params(white_e=40 * 5000.0, full_well_e=5000.0, blooming_decay_px=6.0, read_noise_e=0.0, adc_bits=12)
    out = sensor.apply_sensor(img, p)
    col = out[:, 100].astype(int)
    assert (col[84:116] == 255).all()  # 8 px x 39 full wells of excess fill ~+-14 rows of the column
    assert 100 < col[80] < 255 and 100 < col[119] < 255  # and fade out 18 rows away (the optics reach ~3 px)
    assert (col[:55] == 0).all() and (col[146:] == 0).all()  # beyond the spill window (6 decay lengths)
    assert (out[:, 90] == 0).all()  # not across columns


def test_image_motion_ignores_points_no_camera_images():
    """A point beside a near camera, close to its plane (a solar-array corner at 20 m), is not in any image: it
    must not set the streak (it once asked for a 123953 px kernel). The streak is that of the points in view,
    computed here by finite differences of their projections."""
    from envisat_pose.datagen.sensor import image_velocity_px_s

    f = 1900.0
    in_view = np.array([[1.0, 0.5, 0.0], [-1.0, 0.5, 0.0], [1.0, -0.5, 0.0], [-1.0, -0.5, 0.0]])
    beside = np.array([[15.0, 0.0, -19.99]])  # 1 cm in front of the camera's plane, 15 m to the side
    t_K, R = np.array([0.0, 0.0, 20.0]), np.eye(3)
    w, v = np.array([0.0, 0.05, 0.0]), np.zeros(3)
    speed, _ = image_velocity_px_s(np.vstack([in_view, beside]), R, t_K, w, v, f)
    ref, _ = image_velocity_px_s(in_view, R, t_K, w, v, f)
    assert speed == ref
    # the reference itself: the RMS image speed of the in-view points along their principal axis, their image
    # velocities by finite differences
    dt = 1e-6
    rot = lambda a: np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])  # noqa: E731
    proj = lambda P: f * P[:, :2] / P[:, 2:3]  # noqa: E731
    vel = (proj(t_K + in_view @ rot(w[1] * dt).T) - proj(t_K + in_view)) / dt
    assert ref == pytest.approx(np.sqrt(np.linalg.eigvalsh(vel.T @ vel / len(vel))[-1]), rel=1e-4)
    assert image_velocity_px_s(beside, R, t_K, w, v, f) == (0.0, 0.0)
