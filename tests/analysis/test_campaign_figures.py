"""Campaign figures: the PNGs decode, show data, and carry the paper's colours (grey runs, red P, green sample)."""

import os

import cv2
import numpy as np
import pytest

from envisat_pose.analysis import campaign_figures as cf
from envisat_pose.analysis.stats import block_error_norms, campaign_stats, component_errors


def colour_pixels(img_bgr: np.ndarray, hex_rgb: str, tol: int = 40) -> int:
    """Pixels within tol of a colour in every channel (image in OpenCV's BGR order)."""
    rgb = np.array([int(hex_rgb[i:i + 2], 16) for i in (1, 3, 5)])
    return int(np.all(np.abs(img_bgr[..., ::-1].astype(int) - rgb) <= tol, axis=-1).sum())


def read_png(path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, f"{path} does not decode"
    assert img.std() > 10, f"{path} is blank"
    return img


@pytest.fixture(scope="module")
def campaign():
    rng = np.random.default_rng(20)
    R, T = 25, 300
    t_s = np.arange(T, dtype=float)
    sig = np.array([0.05] * 3 + [1e-4] * 3 + [2e-4] * 3 + [1e-5] * 3) * (1 + 5 * np.exp(-t_s / 60))[:, None]
    x_true = np.zeros((R, T, 12))
    x_true[..., 1] = 50.0
    x_true[..., 6:9] = [0.1, 0.2, -0.3]
    x_hat = x_true + rng.normal(size=(R, T, 12)) * sig
    P = np.zeros((R, T, 12, 12))
    P[..., np.arange(12), np.arange(12)] = sig**2
    dof = np.full((R, T), 24)
    nis = rng.chisquare(24, size=(R, T))
    st = campaign_stats(x_true, x_hat, P, nis, dof, np.zeros(R, bool))
    return t_s, x_true, x_hat, st


def test_error_envelopes_show_grey_runs_red_filter_and_green_sample_3sigma(tmp_path, campaign):
    t_s, x_true, x_hat, st = campaign
    err = component_errors(x_true, x_hat)
    full, bare = tmp_path / "err.png", tmp_path / "bare.png"
    cf.plot_error_envelopes(t_s, err, st.filter_3sigma, st.sample_3sigma, str(full))
    cf.plot_error_envelopes(t_s, None, st.filter_3sigma, None, str(bare))
    img, ctl = read_png(full), read_png(bare)
    assert img.shape[:2] == ctl.shape[:2]
    assert colour_pixels(img, cf.RED_FILTER) > 2000 and colour_pixels(ctl, cf.RED_FILTER) > 2000
    assert colour_pixels(img, cf.GREEN_SAMPLE) > 2000
    assert colour_pixels(ctl, cf.GREEN_SAMPLE) < 50  # the detector tells the curves apart
    # the runs: far more grey than the axes, ticks and labels of the same figure without them
    assert colour_pixels(img, cf.GREY_RUNS, tol=25) > 5 * colour_pixels(ctl, cf.GREY_RUNS, tol=25) + 5000
    assert not [f for f in os.listdir(tmp_path) if f.startswith(".tmp-")]  # written atomically


def test_block_norms_nees_nis_and_rmse_vs_bound_figures(tmp_path, campaign):
    t_s, x_true, x_hat, st = campaign
    norms = block_error_norms(x_true, x_hat)
    cf.plot_block_norms(t_s, norms, st.rmse_block, st.filter_3sigma_block, str(tmp_path / "norms.png"))
    img = read_png(tmp_path / "norms.png")
    assert colour_pixels(img, cf.BLUE_RMSE) > 500 and colour_pixels(img, cf.GREY_RUNS, tol=25) > 5000

    cf.plot_nees_nis(t_s, st.nees_mean, st.nees_bounds, st.nis_mean, st.nis_bounds, str(tmp_path / "nees.png"))
    img = read_png(tmp_path / "nees.png")
    band = "#f9e699"  # BAND_FILL at alpha 0.45 over white
    assert colour_pixels(img, band, tol=20) > 20000 and colour_pixels(img, cf.BLUE_RMSE) > 500

    bound = st.rmse_block / 1.1
    cf.plot_rmse_vs_bound(t_s, st.rmse_block, bound, str(tmp_path / "crlb.png"),
                          filter_3sigma_block=st.filter_3sigma_block)
    cf.plot_rmse_vs_bound(t_s, st.rmse_block, None, str(tmp_path / "nocrlb.png"))
    img, ctl = read_png(tmp_path / "crlb.png"), read_png(tmp_path / "nocrlb.png")
    # the dashed black bound adds dark pixels inside the axes beyond the text both figures share
    assert colour_pixels(img, cf.BLACK_BOUND, tol=60) > colour_pixels(ctl, cf.BLACK_BOUND, tol=60) + 1000
    assert colour_pixels(img, cf.RED_FILTER) > 300 and colour_pixels(ctl, cf.RED_FILTER) < 50


def test_rate_sweep_figure(tmp_path):
    rate_hz = np.array([1.0, 0.05, 0.2, 10.0, 0.5, 2.0])
    rmse = np.outer(1.0 / np.sqrt(rate_hz), [0.01, 1e-4, 1e-3, 1e-5])
    rmse[1] = np.nan  # no converged run at 0.05 Hz
    cf.plot_rate_sweep(rate_hz, rmse, str(tmp_path / "sweep.png"), bound_block=rmse / 1.2,
                       diverged_share=np.array([0, 1.0, 0.3, 0, 0, 0]))
    img = read_png(tmp_path / "sweep.png")
    assert colour_pixels(img, cf.BLUE_RMSE) > 300 and colour_pixels(img, cf.RED_FILTER) > 100


def test_many_runs_are_thinned_and_still_drawn(tmp_path):
    rng = np.random.default_rng(21)
    R, T = 400, 5000
    t_s = np.arange(T, dtype=float)
    err = rng.normal(size=(R, T, 12)) * 0.01
    three = np.full((T, 12), 0.03)
    cf.plot_error_envelopes(t_s, err, three, three * 1.05, str(tmp_path / "big.png"), max_runs=50, max_points=500)
    img = read_png(tmp_path / "big.png")
    assert colour_pixels(img, cf.GREY_RUNS, tol=25) > 10000
