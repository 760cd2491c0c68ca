"""The blueprint every recording carries, read back from the written .rrd (its blueprint store, Rerun's own reader):
each time plot spans the whole run at load. Without an infinite x-axis view range the viewer opens a plot on the
~50 s before the time cursor, which a file opens at its end: an estimate's 600 s errors, opened in the web viewer,
showed only their last ~50 s (their first 150 s of +-3 sigma bands not drawn; headless Chromium, 2026-12-07)."""

import numpy as np
import rerun as rr

from envisat_pose.analysis import recording
from envisat_pose.analysis.recording import TrackRecorder
from envisat_pose.contracts import Estimates
from envisat_pose.geometry import load_camera


def estimates(R=2, T=6):
    t_s = np.arange(T) * 2.0
    x_true = np.zeros((R, T, 12))
    x_true[..., 1] = 50.0
    x_hat = x_true + 0.01 * np.random.default_rng(0).standard_normal((R, T, 12))
    P = np.broadcast_to(1e-4 * np.eye(12), (R, T, 12, 12)).copy()
    return Estimates(t_s=t_s, x_true=x_true, x_hat=x_hat, P=P, n_meas=np.full((R, T), 8), nis=np.ones((R, T)),
                     nis_dof=np.full((R, T), 24), diverged=np.zeros(R, bool), config_json="{}")


def time_series_views(path) -> dict:
    """{view name: its TimeAxis columns ({} where it has none)} of every TimeSeries view in the file's blueprint."""
    reader = rr.chunk.RrdReader(str(path))
    (store,) = reader.blueprints()
    names, axes = {}, {}
    for chunk in reader.stream(store=store).collect().stream():
        batch = chunk.to_record_batch()
        cols = {n: batch.column(n).to_pylist()[-1] for n in batch.schema.names if ":" in n}
        view = chunk.entity_path.removesuffix("/TimeAxis")
        if chunk.entity_path.endswith("/TimeAxis"):
            axes[view] = cols
        elif cols.get("ViewBlueprint:class_identifier") == ["TimeSeries"]:
            names[view] = cols["ViewBlueprint:display_name"][0]
    return {name: axes.get(view, {}) for view, name in names.items()}


def assert_whole_run(views: dict) -> None:
    assert views
    for name, axis in views.items():
        assert axis.get("TimeAxis:view_range") == [{"start": None, "end": None}], f"{name!r} opens on a window"


def test_every_recordings_time_plots_span_the_whole_run(tmp_path):
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate_truth

    recording.write_truth_recording(str(tmp_path / "truth.rrd"), simulate_truth(scenario_config("default",
                                                                                               duration_s=4.0)))
    views = time_series_views(tmp_path / "truth.rrd")
    assert set(views) == {"range (m)", "visible / in-frame corners"}
    assert_whole_run(views)

    est = estimates()
    recording.write_estimates_recording(str(tmp_path / "est.rrd"), est)
    views = time_series_views(tmp_path / "est.rrd")
    assert len(views) == 13 and "position_m x error" in views and "NEES (12 dof): mean over runs, 95 % band" in views
    assert_whole_run(views)

    recording.write_campaign_recording(str(tmp_path / "mc.rrd"), est.t_s, est.x_true[0], est.x_hat[0], est.P[0],
                                       est.x_hat - est.x_true, np.ones((6, 12)), np.ones((6, 12)))
    assert_whole_run(time_series_views(tmp_path / "mc.rrd"))

    rec = TrackRecorder(f"save:{tmp_path / 'run.rrd'}", load_camera().scaled(64, 64), with_truth=True)
    rec.close()
    views = time_series_views(tmp_path / "run.rrd")
    assert len(views) == 6
    assert_whole_run(views)
