"""Plots: the MRP error compares estimate and truth on one set; the PNGs decode and show the plotted data."""

import numpy as np

from envisat_pose.analysis.plots import estimate_errors, plot_estimate, plot_states
from envisat_pose.attitude import mrp_error_angle_rad


def test_mrp_error_is_small_when_the_estimate_sits_on_the_shadow_set():
    p_true = np.array([0.0, 0.0, 0.999])
    p_near = np.array([0.0, 0.0, 1.001])  # 0.23 deg away, past |p| = 1
    p_hat = -p_near / np.dot(p_near, p_near)  # the estimate reported on the short set: far away as numbers
    x_true = np.zeros((1, 1, 12))
    x_hat = np.zeros((1, 1, 12))
    x_true[0, 0, 6:9], x_hat[0, 0, 6:9] = p_true, p_hat
    err = estimate_errors(x_true, x_hat)
    assert np.linalg.norm(err[0, 0, 6:9]) < 0.003
    assert np.degrees(mrp_error_angle_rad(p_hat, p_true)) < 0.25


def colour_pixels(img_bgr, rgb, tol=40):
    """Pixels within `tol` per channel of the colour rgb (0-255). (H, W) bool."""
    return np.all(np.abs(img_bgr.astype(int) - np.array(rgb[::-1])) <= tol, axis=-1)


C0, C3 = (31, 119, 180), (214, 39, 40)  # matplotlib's default blue and red


def test_plots_are_written_and_show_the_data(tmp_path):
    import cv2

    rng = np.random.default_rng(0)
    T, R = 50, 3
    t_s = np.arange(T, dtype=float)
    x_true = np.zeros((R, T, 12))
    x_true[..., 1] = 50.0
    x_hat = x_true + rng.normal(0, 0.01, x_true.shape)
    P = np.broadcast_to(np.eye(12) * 1e-4, (R, T, 12, 12))
    plot_estimate(t_s, x_true, x_hat, P, str(tmp_path / "est.png"))
    plot_states(t_s, x_true[0], str(tmp_path / "run.png"), visible=np.ones((T, 8), bool))
    est, run = cv2.imread(str(tmp_path / "est.png")), cv2.imread(str(tmp_path / "run.png"))
    assert est is not None and run is not None, "not decodable PNGs"
    assert est.shape == (1300, 1300, 3)  # 13 x 13 in at 100 dpi
    assert run.shape == (1331, 1430, 3)  # 13 x 12.1 in at 110 dpi (5 rows with the visible corners)
    for img in (est, run):
        assert img.std() > 20 and np.mean(img > 250) < 0.98  # not blank
    # the errors of run 0 (blue) and the filter's 3 sigma (red) are drawn in each of the 12 state panels
    h, w = est.shape[:2]
    for i in range(12):
        r, c = divmod(i, 3)
        cell = est[r * h // 5 : (r + 1) * h // 5, c * w // 3 : (c + 1) * w // 3]
        assert colour_pixels(cell, C0).sum() > 100 and colour_pixels(cell, C3).sum() > 100, i
    # the states (blue) are drawn in each panel of the truth plot, and the visible-corner count too
    h, w = run.shape[:2]
    for i in range(13):
        r, c = divmod(i, 3)
        cell = run[r * h // 5 : (r + 1) * h // 5, c * w // 3 : (c + 1) * w // 3]
        assert colour_pixels(cell, C0).sum() > 100, i


def test_a_plot_without_data_fails_the_check(tmp_path):
    """The check above can fail: all-NaN states draw no lines, so no panel shows the data colour."""
    import cv2

    t_s = np.arange(20, dtype=float)
    plot_states(t_s, np.full((20, 12), np.nan), str(tmp_path / "empty.png"))
    img = cv2.imread(str(tmp_path / "empty.png"))
    assert colour_pixels(img, C0).sum() < 50


def test_the_estimate_figures_legend_hides_no_panel(tmp_path, monkeypatch):
    """The legend (run 0's error, the filter's and the sample's 3 sigma, the frames without an estimate) sits
    where it covers no panel's plotting area: a short run's first seconds are not hidden under it."""
    import matplotlib.pyplot as plt

    figs, close = [], plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: (figs.append(fig), close(fig)))
    T, R = 40, 3
    t_s = np.arange(T, dtype=float)
    x_true = np.zeros((R, T, 12))
    x_true[..., 1] = 50.0
    x_hat = x_true + np.random.default_rng(1).normal(0, 0.01, x_true.shape)
    x_hat[:, :5] = np.nan  # a cold start: no estimate in the first frames
    P = np.broadcast_to(np.eye(12) * 1e-4, (R, T, 12, 12))
    plot_estimate(t_s, x_true, x_hat, P, str(tmp_path / "est.png"))
    (fig,) = figs
    fig.canvas.draw()
    legends = [ax.get_legend() for ax in fig.axes if ax.get_legend()] + list(fig.legends)
    assert len(legends) == 1
    labels = [t.get_text() for t in legends[0].get_texts()]
    assert labels == ["error, run 0", "filter 3 sigma (P)", "Monte Carlo 3 sigma", "no estimate"]
    box = legends[0].get_window_extent()
    assert not [i for i, ax in enumerate(fig.axes) if ax.axison and box.overlaps(ax.bbox)]


def drawn_figures(monkeypatch) -> list:
    """The figures the plots close (each plot closes its figure once saved): read their labels, not pixels."""
    import matplotlib.pyplot as plt

    figs, close = [], plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: (figs.append(fig), close(fig)))
    return figs


def test_the_truth_plot_counts_any_targets_keypoints_on_an_axis_that_holds_them(tmp_path, monkeypatch):
    """A 12-keypoint target's visible count (9 to 12) was drawn on ENVISAT's axis (-0.5..8.5, "visible corners"):
    above the panel, an empty plot. Its axis holds 0..K and says what is counted; ENVISAT's keeps "corners"."""
    figs = drawn_figures(monkeypatch)
    T = 30
    t_s = np.arange(T, dtype=float)
    visible = np.zeros((T, 12), bool)
    visible[:, :10] = True
    plot_states(t_s, np.zeros((T, 12)), str(tmp_path / "k.png"), visible=visible, points="keypoints")
    plot_states(t_s, np.zeros((T, 12)), str(tmp_path / "e.png"), visible=np.ones((T, 8), bool))
    (kp, env) = [f.axes[12] for f in figs]
    assert kp.get_ylabel() == "visible keypoints (of 12)" and env.get_ylabel() == "visible corners (of 8)"
    assert kp.get_ylim()[0] < 0 and 12 < kp.get_ylim()[1] < 13 and 8 < env.get_ylim()[1] < 9
    figs[0].canvas.draw()
    assert all(float(t).is_integer() for t in kp.get_yticks()), kp.get_yticks()  # a count's ticks: no 7.5


def test_the_estimate_figures_state_labels_give_their_units_in_brackets(tmp_path, monkeypatch):
    """Every axis of the estimate's figure names its unit as the others do ("rho_x [cm]", "t [min]"), not
    "rho_x cm"; the MRP, without a unit, has none."""
    figs = drawn_figures(monkeypatch)
    T, R = 20, 2
    x_true = np.zeros((R, T, 12))
    x_true[..., 1] = 50.0
    x_hat = x_true + np.random.default_rng(2).normal(0, 0.01, x_true.shape)
    plot_estimate(np.arange(T, dtype=float), x_true, x_hat, np.broadcast_to(np.eye(12) * 1e-4, (R, T, 12, 12)),
                  str(tmp_path / "est.png"))
    (fig,) = figs
    labels = [ax.get_ylabel() for ax in fig.axes[:12]]
    assert labels[:6] == ["rho_x [cm]", "rho_y [cm]", "rho_z [cm]", "rho'_x [mm/s]", "rho'_y [mm/s]", "rho'_z [mm/s]"]
    assert labels[6:9] == ["p_1", "p_2", "p_3"] and labels[9] == "w_r1 [deg/s]"
