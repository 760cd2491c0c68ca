"""Campaign figures: what each one plots, read off the figure as drawn (its lines, collections and labels): the
inputs in the display units (m, mm/s, deg, deg/s; t in min), each curve in the paper's colour (grey runs, red
filter 3-sigma, green sample 3-sigma, blue RMSE, black PCRLB), and the PNG that decodes."""

import os

import cv2
import numpy as np
import pytest
from matplotlib.colors import same_color

from envisat_pose.analysis import campaign_figures as cf
from envisat_pose.analysis.stats import block_error_norms, campaign_stats, component_errors

# the figures' display units per state component and block, written out here (not read from the module)
UNITS = ("m",) * 3 + ("mm/s",) * 3 + ("deg",) * 3 + ("deg/s",) * 3
SCALE = np.array([1.0] * 3 + [1e3] * 3 + [180.0 / np.pi] * 6)
BLOCK_UNITS = ("m", "mm/s", "deg", "deg/s")
BLOCK_SCALE = np.array([1.0, 1e3, 180.0 / np.pi, 180.0 / np.pi])


@pytest.fixture
def drawn(monkeypatch):
    """The figures as drawn: every figure the module writes, recorded before it is written (and closed)."""
    figs, real = [], cf._save

    def save(fig, path, dpi=100):
        figs.append(fig)
        real(fig, path, dpi)

    monkeypatch.setattr(cf, "_save", save)
    return figs


def read_png(path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, f"{path} does not decode"
    assert img.std() > 10, f"{path} is blank"
    return img


def lines(ax, colour, ls=None):
    """The axes' lines drawn in a colour (and a line style)."""
    return [ln for ln in ax.get_lines() if same_color(ln.get_color(), colour)
            and (ls is None or ln.get_linestyle() == ls)]


def assert_curves(ax, colour, t, ys, ls=None):
    """The axes hold exactly the curves ys (each (T,)) against t in that colour, in any order."""
    got = lines(ax, colour, ls)
    assert len(got) == len(ys), (colour, len(got), len(ys))
    for ln, y in zip(sorted(got, key=lambda g: float(np.nansum(g.get_ydata()))), sorted(ys, key=np.nansum)):
        np.testing.assert_allclose(ln.get_xdata(), t, rtol=1e-12)
        np.testing.assert_allclose(ln.get_ydata(), y, rtol=1e-9, atol=0)


def run_segments(ax) -> np.ndarray:
    """The grey runs' LineCollection as (R, T, 2)."""
    runs = [c for c in ax.collections if same_color(c.get_colors()[0], cf.GREY_RUNS)]
    assert len(runs) == 1
    return np.array(runs[0].get_segments())


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
    return t_s, x_true, x_hat, st, sig


def test_error_envelopes_show_grey_runs_red_filter_and_green_sample_3sigma(tmp_path, campaign, drawn):
    """Per component: every run's error (grey), +- the filter's 3-sigma (red dashed; for position, velocity and
    rate 3 sqrt(P_ii) of the campaign's P, checked here), +- the sample 3-sigma (green), in display units against
    minutes; without runs and sample, only the red bounds."""
    t_s, x_true, x_hat, st, sig = campaign
    err = component_errors(x_true, x_hat)
    full, bare = tmp_path / "err.png", tmp_path / "bare.png"
    cf.plot_error_envelopes(t_s, err, st.filter_3sigma, st.sample_3sigma, str(full))
    cf.plot_error_envelopes(t_s, None, st.filter_3sigma, None, str(bare))
    read_png(full), read_png(bare)
    assert not [f for f in os.listdir(tmp_path) if f.startswith(".tmp-")]  # written atomically
    fig, ctl = drawn
    t_min = t_s / 60.0
    not_attitude = np.r_[0:6, 9:12]
    np.testing.assert_allclose(st.filter_3sigma[:, not_attitude], 3 * sig[:, not_attitude], rtol=1e-9)
    for i in range(12):
        ax, ax0 = fig.axes[i], ctl.axes[i]
        assert ax.get_ylabel().endswith(f"[{UNITS[i]}]"), ax.get_ylabel()
        f3, m3 = st.filter_3sigma[:, i] * SCALE[i], st.sample_3sigma[:, i] * SCALE[i]
        assert_curves(ax, cf.RED_FILTER, t_min, [f3, -f3], ls="--")
        assert_curves(ax, cf.GREEN_SAMPLE, t_min, [m3, -m3])
        seg = run_segments(ax)
        assert seg.shape == (25, 300, 2)
        np.testing.assert_allclose(seg[..., 0], np.broadcast_to(t_min, (25, 300)))
        np.testing.assert_allclose(seg[..., 1], err[..., i] * SCALE[i], rtol=1e-12)
        assert_curves(ax0, cf.RED_FILTER, t_min, [f3, -f3], ls="--")
        assert not lines(ax0, cf.GREEN_SAMPLE) and not ax0.collections
    assert [ax.get_xlabel() for ax in fig.axes[9:12]] == ["t [min]"] * 3
    assert not legend_over_data(fig) and not legend_over_data(ctl)


def legend_over_data(fig) -> list[int]:
    """The panels (indices) whose plotting area a legend of the figure covers, as drawn: a legend must name the
    curves without hiding any of them."""
    fig.canvas.draw()
    legends = [*fig.legends, *(ax.get_legend() for ax in fig.axes if ax.get_legend())]
    assert legends, "no legend"
    boxes = [lg.get_window_extent() for lg in legends]
    return [i for i, ax in enumerate(fig.axes) if ax.axison and any(b.overlaps(ax.bbox) for b in boxes)]


def test_block_norms_nees_nis_and_rmse_vs_bound_figures(tmp_path, campaign, drawn):
    t_s, x_true, x_hat, st, _ = campaign
    t_min = t_s / 60.0
    norms = block_error_norms(x_true, x_hat)
    cf.plot_block_norms(t_s, norms, st.rmse_block, st.filter_3sigma_block, str(tmp_path / "norms.png"))
    cf.plot_nees_nis(t_s, st.nees_mean, st.nees_bounds, st.nis_mean, st.nis_bounds, str(tmp_path / "nees.png"))
    bound = st.rmse_block / 1.1
    cf.plot_rmse_vs_bound(t_s, st.rmse_block, bound, str(tmp_path / "crlb.png"),
                          filter_3sigma_block=st.filter_3sigma_block)
    cf.plot_rmse_vs_bound(t_s, st.rmse_block, None, str(tmp_path / "nocrlb.png"))
    for name in ("norms", "nees", "crlb", "nocrlb"):
        read_png(tmp_path / f"{name}.png")
    fig_norms, fig_nees, fig_crlb, fig_ctl = drawn

    # the norms: every run's block error norm (grey), the RMSE (blue), the filter's 3-sigma (red dashed), log y
    for b in range(4):
        ax = fig_norms.axes[b]
        assert ax.get_yscale() == "log" and ax.get_ylabel().endswith(f"[{BLOCK_UNITS[b]}]")
        assert_curves(ax, cf.BLUE_RMSE, t_min, [st.rmse_block[:, b] * BLOCK_SCALE[b]])
        assert_curves(ax, cf.RED_FILTER, t_min, [st.filter_3sigma_block[:, b] * BLOCK_SCALE[b]], ls="--")
        np.testing.assert_allclose(run_segments(ax)[..., 1], np.maximum(norms[..., b] * BLOCK_SCALE[b], 1e-12))

    # NEES and NIS: the means (blue) inside their chi-square bands (shaded from the lower to the upper bound)
    for ax, mean, bounds in zip(fig_nees.axes, (st.nees_mean, st.nis_mean), (st.nees_bounds, st.nis_bounds)):
        assert ax.get_yscale() == "log"
        assert_curves(ax, cf.BLUE_RMSE, t_min, [mean])
        band = [c for c in ax.collections if same_color(c.get_facecolor()[0][:3], cf.BAND_FILL)]
        assert len(band) == 1
        y = band[0].get_paths()[0].vertices[:, 1]
        bnd = np.broadcast_to(bounds, (len(t_s), 2))
        assert y.min() == pytest.approx(bnd[:, 0].min()) and y.max() == pytest.approx(bnd[:, 1].max())
    # the campaign's chi-square: NEES of 12 dof averaged over 25 runs, its mean near 12 inside the band
    assert np.all(st.nees_bounds[..., 0] < 12) and np.all(st.nees_bounds[..., 1] > 12)

    # RMSE against the bound: blue, the PCRLB black dashed, the filter's sigma (3-sigma / 3) red dotted; without
    # a bound and a filter sigma, neither is drawn
    for b in range(4):
        ax, ax0 = fig_crlb.axes[b], fig_ctl.axes[b]
        s = BLOCK_SCALE[b]
        assert ax.get_ylabel().endswith(f"[{BLOCK_UNITS[b]}]")
        assert_curves(ax, cf.BLUE_RMSE, t_min, [st.rmse_block[:, b] * s])
        assert_curves(ax, cf.BLACK_BOUND, t_min, [bound[:, b] * s], ls="--")
        assert_curves(ax, cf.RED_FILTER, t_min, [st.filter_3sigma_block[:, b] / 3.0 * s], ls=":")
        assert_curves(ax0, cf.BLUE_RMSE, t_min, [st.rmse_block[:, b] * s])
        assert not lines(ax0, cf.BLACK_BOUND) and not lines(ax0, cf.RED_FILTER)


def test_rate_sweep_figure(tmp_path, drawn):
    """Per block the RMSE (blue) and the bound (black dashed) against the rate in increasing order, log-log, a
    rate without a converged run left as a gap; the diverged share in percent (red) on its own axes."""
    rate_hz = np.array([1.0, 0.05, 0.2, 10.0, 0.5, 2.0])
    rmse = np.outer(1.0 / np.sqrt(rate_hz), [0.01, 1e-4, 1e-3, 1e-5])
    rmse[1] = np.nan  # no converged run at 0.05 Hz
    share = np.array([0, 1.0, 0.3, 0, 0, 0])
    cf.plot_rate_sweep(rate_hz, rmse, str(tmp_path / "sweep.png"), bound_block=rmse / 1.2, diverged_share=share)
    read_png(tmp_path / "sweep.png")
    (fig,) = drawn
    order = np.argsort(rate_hz)
    r = rate_hz[order]
    assert np.all(np.diff(r) > 0)
    for b in range(4):
        ax = fig.axes[b]
        assert ax.get_xscale() == ax.get_yscale() == "log" and ax.get_ylabel().endswith(f"[{BLOCK_UNITS[b]}]")
        (blue,) = lines(ax, cf.BLUE_RMSE)
        np.testing.assert_allclose(blue.get_xdata(), r)
        np.testing.assert_allclose(blue.get_ydata(), rmse[order, b] * BLOCK_SCALE[b])  # NaN where NaN: a gap
        (black,) = lines(ax, cf.BLACK_BOUND, "--")
        np.testing.assert_allclose(black.get_ydata(), rmse[order, b] / 1.2 * BLOCK_SCALE[b])
    (red,) = lines(fig.axes[4], cf.RED_FILTER)
    np.testing.assert_allclose(red.get_xdata(), r)
    np.testing.assert_allclose(red.get_ydata(), [100.0, 30.0, 0.0, 0.0, 0.0, 0.0])
    assert fig.axes[4].get_ylabel() == "diverged runs [%]"


def test_many_runs_are_thinned_and_still_drawn(tmp_path, drawn):
    """400 runs of 5000 steps: the first 50 runs, every 10th step (500 points a line), the same samples of the
    input as a plain slice takes."""
    rng = np.random.default_rng(21)
    R, T = 400, 5000
    t_s = np.arange(T, dtype=float)
    err = rng.normal(size=(R, T, 12)) * 0.01
    three = np.full((T, 12), 0.03)
    cf.plot_error_envelopes(t_s, err, three, three * 1.05, str(tmp_path / "big.png"), max_runs=50, max_points=500)
    read_png(tmp_path / "big.png")
    (fig,) = drawn
    for i in (0, 4, 7, 11):
        seg = run_segments(fig.axes[i])
        assert seg.shape == (50, 500, 2)
        np.testing.assert_allclose(seg[..., 0], np.broadcast_to(t_s[::10] / 60.0, (50, 500)))
        np.testing.assert_allclose(seg[..., 1], err[:50, ::10, i] * SCALE[i])
    assert_curves(fig.axes[7], cf.RED_FILTER, t_s[::10] / 60.0, [three[::10, 7] * SCALE[7], -three[::10, 7] * SCALE[7]],
                  ls="--")
