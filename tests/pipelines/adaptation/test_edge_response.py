"""The camera response (response curve and blur) from its own frames (pipelines/adaptation/edge_response.py) and
the edge cue in linear light (pipelines/adaptation/edge_range.py with `light`).

The frames are drawn here in closed form, not by the code under test: a convex polygon's light is the product
of each edge's Gaussian-blurred half-plane, Phi(distance / sigma) (exact for one straight edge; the stations
keep far enough from the corners that the others' factors are 1 to 1e-4), integrated over each pixel by 4 x 4
sub-samples, on a dark sky with a black-level pedestal, plus the sensor's noise in light, then stored through the
response by its closed form (IEC 61966-2-1's sRGB, or v^(1/g)) and rounded to 8 bits. Every draw comes from an
explicit seed."""

import functools

import numpy as np
import pytest
from scipy.special import ndtr

from envisat_pose.camera_response import LINEAR, SRGB, Response, parse_response
from envisat_pose.pipelines.adaptation.edge_range import edge_stations
from envisat_pose.pipelines.adaptation.edge_response import estimate_response

HEX = np.array([[150.3, 80.6], [330.2, 101.1], [392.5, 210.0], [316.7, 335.4], [135.9, 314.8], [92.4, 190.2]])
RESPONSES = {"linear": None, "srgb": "srgb", "gamma 1.8": 1.8, "gamma 2.4": 2.4}
FRAMES, NOISE, LIGHT, SKY = 12, 0.004, 0.7, 0.03
SIGMAS = (0.3, 1.0, 2.5)


def store(light: np.ndarray, kind) -> np.ndarray:
    """Light (0-1) as the 8-bit value a camera with response `kind` stores (None linear, 'srgb', a gamma)."""
    v = np.clip(light, 0.0, 1.0)
    if kind == "srgb":
        v = np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)
    elif kind is not None:
        v = v ** (1.0 / kind)
    return np.clip(np.rint(255.0 * v), 0, 255).astype(np.uint8)


def polygon_light(poly: np.ndarray, sigma_px: float, size: int = 480, ss: int = 4) -> np.ndarray:
    """The polygon's light (LIGHT inside, SKY outside) blurred by a Gaussian PSF of sigma_px, per pixel."""
    f = ((np.arange(size * ss) + 0.5) / ss - 0.5).astype(np.float32)
    X, Y = np.meshgrid(f, f)
    cover = np.ones_like(X)
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        n = np.array([b[1] - a[1], a[0] - b[0]]) / np.hypot(*(b - a))
        n *= np.sign((poly.mean(axis=0) - a) @ n)  # inward
        cover *= ndtr(((X - a[0]) * n[0] + (Y - a[1]) * n[1]) / sigma_px)
    return SKY + (LIGHT - SKY) * cover.reshape(size, ss, size, ss).mean(axis=(1, 3))


@functools.cache
def lights(sigma: float, n: int) -> tuple[list, np.ndarray]:
    """n frames' light (the polygon shifted by up to 3 px, seeded by the case) and their corners (n, 8, 2): the same
    under every response."""
    shifts = np.random.default_rng([49, SIGMAS.index(sigma)]).uniform(-3.0, 3.0, (n, 2))
    corners = np.array([np.concatenate([HEX + d, (HEX + d).mean(axis=0) + [[0.0, 0.0], [1.0, 0.5]]])
                        for d in shifts])
    return [polygon_light(HEX + d, sigma) for d in shifts], corners


def case(name: str, sigma: float, n: int = FRAMES) -> tuple[list, np.ndarray, np.ndarray]:
    """(images, corners (n, 8, 2), use (n, 8)): the n frames' light stored through the response `name` with the
    sensor's noise in light, seeded by the case."""
    light, corners = lights(sigma, n)
    noise = np.random.default_rng([49, SIGMAS.index(sigma), list(RESPONSES).index(name)])
    ims = [store(v + noise.normal(0.0, NOISE, v.shape), RESPONSES[name]) for v in light]
    return ims, corners, np.ones((n, 8), bool)


def mean_offset_px(ims, corners, use, light, blur_px):
    return float(np.mean(np.concatenate([edge_stations(im, c, u, light=light, blur_px=blur_px).offset_px
                                         for im, c, u in zip(ims, corners, use)])))


@pytest.mark.parametrize("name", list(RESPONSES))
def test_the_edge_in_linear_light_sits_on_the_true_step(name):
    """Linearized by the camera's response (its TOML's), the area method's edge is within 0.02 px of the drawn
    outline at every PSF; read in the stored values it is not (an encoded bright edge reads outward)."""
    response = parse_response(RESPONSES[name] or "linear", "response")
    for sigma in SIGMAS:
        ims, corners, use = case(name, sigma, 2)
        assert abs(mean_offset_px(ims, corners, use, response, sigma)) < 0.02, (name, sigma)
        if name != "linear" and sigma < 2.0:  # the stored values' own guards cannot reach a 2.5 px blur
            assert mean_offset_px(ims, corners, use, None, None) > 0.1, (name, sigma)


@pytest.mark.slow  # ~100 s on the loaded 2-core machine: 36 frames drawn, 32 linearizations of each
@pytest.mark.parametrize("name", list(RESPONSES))
def test_the_response_and_blur_are_read_from_the_frames(name):
    """estimate_response recovers the response where the blur shows it (1 and 2.5 px): linear by name; sRGB by name
    or as a power within 0.1 of its nominal 2.2; a gamma's power within 0.1 (the curve chosen may be sRGB where
    the power cannot be told from 2.2). Linearized by what it found, the edge is
    within 0.05 px of the true step (0.03 of error in the power moves a 2.5 px blur's edge by 0.02 px: adapt
    carries that as the scale's response term). At 0.3 px no power is claimed and a named curve is chosen. The PSF's
    sigma within 0.1 px throughout."""
    kind = RESPONSES[name]
    for sigma in SIGMAS:
        ims, corners, use = case(name, sigma)
        fit = estimate_response(ims, corners, use)
        assert fit.stations > 1000 and fit.psf_sigma_px == pytest.approx(sigma, abs=0.1), (name, sigma, fit)
        if sigma < 0.5:
            assert fit.gamma is None and fit.response in (LINEAR, SRGB), (name, sigma, fit)
            continue
        if kind is None:
            assert fit.response == LINEAR, (name, sigma, fit)
        elif kind == "srgb":
            assert fit.response == SRGB or abs(fit.response.gamma - 2.2) < 0.1, (name, sigma, fit)
        else:
            assert abs(fit.gamma - kind) < 0.1 and fit.response != LINEAR, (name, sigma, fit)
        assert abs(mean_offset_px(ims, corners, use, fit.response, fit.psf_sigma_px)) < 0.05, (name, sigma, fit)


def test_the_response_curves_invert_and_parse():
    v = np.linspace(0.0, 1.0, 1001)
    for r in (LINEAR, SRGB, Response("gamma", 2.2)):
        assert np.allclose(r.decode(r.encode(v)), v, atol=1e-12)
    assert SRGB.encode(np.array([0.0031308, 0.5]))[1] == pytest.approx(1.055 * 0.5 ** (1 / 2.4) - 0.055)
    assert parse_response(2.2, "x") == Response("gamma", 2.2) == parse_response("gamma 2.2", "x")
    assert parse_response(1, "x") == LINEAR and parse_response("sRGB", "x") == SRGB
    for bad in ("log", True, 9.0, "gamma x"):
        with pytest.raises(Exception, match="response|x"):
            parse_response(bad, "x")


def test_an_edge_shorter_than_its_margins_gives_no_station_and_no_error():
    """A wide blur grows the stations' distance from an edge's ends (reach + 6 px: 17 px at a 3 px sigma): an
    edge of 30-34 px then holds none, which must leave it out, not fail."""
    tri = np.array([[100.0, 100.0], [132.0, 100.0], [116.0, 72.3]])  # edges of 32 px
    corners = np.concatenate([tri, tri.mean(axis=0) + np.zeros((5, 2))])
    img = store(polygon_light(tri, 3.0, size=200, ss=2), None)
    st = edge_stations(img, corners, np.ones(8, bool), light=LINEAR, blur_px=3.0)
    assert len(st.offset_px) == 0


@pytest.mark.parametrize("true_gamma", [1.03, 1.47, 1.83, 2.61])
def test_the_grid_minimum_is_refined_to_the_parabolas_vertex(true_gamma):
    """A cost that is a parabola in the power has its minimum found exactly between grid points (a half-step error
    passed the end-to-end tolerance of 0.1, the grid's step)."""
    from envisat_pose.pipelines.adaptation.edge_response import GAMMA_GRID, grid_minimum

    assert grid_minimum(3.0 * (GAMMA_GRID - true_gamma) ** 2 + 0.7) == pytest.approx(true_gamma, abs=1e-9)


def test_the_response_chosen_at_the_edges_of_its_rule():
    """Linear within NAMED_Z = 2 standard errors of power 1, sRGB within 2 of 2.2 or where its asymmetry is no
    larger, else the fitted power: each rule on both sides of its edge."""
    from envisat_pose.pipelines.adaptation.edge_response import choose_response

    worse_srgb = {"srgb": {"pooled": 0.5}, "linear": {"pooled": 0.4}, "at_gamma": 0.1}
    assert choose_response(1.079, 0.04, worse_srgb) == LINEAR
    assert choose_response(1.081, 0.04, worse_srgb) == Response("gamma", 1.081)
    assert choose_response(2.279, 0.04, worse_srgb) == SRGB
    assert choose_response(2.281, 0.04, worse_srgb) == Response("gamma", 2.281)
    assert choose_response(2.281, 0.04, {**worse_srgb, "at_gamma": 0.5}) == SRGB  # sRGB's asymmetry as small
