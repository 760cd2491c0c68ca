"""The library runs the job the verb runs (issue 39): a named scenario resolves into the complete job in one place
(pipelines/jobs.py; each config's from_scenario), and for every verb with a pipeline (simulate, estimate,
montecarlo, run, track) the verb and the Python call on the same inputs and seed write the same arrays (NaN where
NaN). Small jobs: seconds of simulated time, a few runs, small frames."""

import os

import numpy as np
import pytest

from envisat_pose.app.cli import main


def same_arrays(a, b, skip=()) -> None:
    """Two .npz files hold the same keys and equal arrays (NaN where NaN)."""
    with np.load(a, allow_pickle=False) as za, np.load(b, allow_pickle=False) as zb:
        assert sorted(za.files) == sorted(zb.files)
        for k in za.files:
            if k not in skip:
                np.testing.assert_array_equal(za[k], zb[k], err_msg=k)


def test_a_scenario_resolves_into_the_job_the_verb_runs():
    """What the verbs take from a scenario: the tuned [filter] table under the tracker's, the gravity-gradient
    switch and orbit for track, the duration and rate for run, the eclipse outages for montecarlo."""
    from envisat_pose import named_scenarios
    from envisat_pose.pipelines.campaigns.campaign import MonteCarloConfig
    from envisat_pose.pipelines.jobs import resolve_job
    from envisat_pose.pipelines.runs.run_config import RunConfig
    from envisat_pose.pipelines.runs.track import TrackConfig

    q = named_scenarios.scenario_tables("default")["filter"]
    run = RunConfig.from_scenario("default", overrides={"tracker.roi.enabled": False}, duration_s=3.0)
    assert run.duration_s == 3.0 and not run.tracker.roi.enabled and run.weights and run.image.sun_dir is not None
    assert all(getattr(run.filter, k) == pytest.approx(v) for k, v in q.items() if not isinstance(v, dict))
    track = TrackConfig.from_scenario("gravity-gradient", rate_hz=2.0)
    assert track.gravity_gradient and track.rate_hz == 2.0 and track.orbit is not None and track.weights
    mc = MonteCarloConfig.from_scenario("eclipse", runs=2)
    assert mc.measurement.outages_s and mc.runs == 2
    assert MonteCarloConfig(scenario="eclipse") == mc.__class__.from_scenario("eclipse")  # the class resolves it too
    assert resolve_job("simulate", "close-25m", seed=4).relative.rho0_C_m == (0.0, 25.0, 0.0)


def scenario_names():
    from envisat_pose import named_scenarios

    return named_scenarios.names()


@pytest.mark.parametrize("name", scenario_names())
def test_the_plain_constructor_with_a_scenario_is_the_scenarios_job(name):
    """Cfg(scenario=NAME) and Cfg.from_scenario(NAME) are one job for every config with a scenario field: the
    gravity-gradient switch, the orbit and the filter's tuning of track, the duration, rate and filter of run, the
    duration, tables and eclipse outages of montecarlo (the plain constructor once took only part of them)."""
    from envisat_pose.pipelines.campaigns.campaign_config import MonteCarloConfig
    from envisat_pose.pipelines.runs.run_config import RunConfig, finish_config
    from envisat_pose.pipelines.runs.track import TrackConfig

    track = TrackConfig.from_scenario(name)
    assert TrackConfig(scenario=name, weights=track.weights) == track
    run = RunConfig.from_scenario(name)
    assert finish_config(RunConfig(scenario=name, weights=run.weights, workers=run.workers)) == run
    assert MonteCarloConfig(scenario=name) == MonteCarloConfig.from_scenario(name)


def test_the_plain_constructor_and_from_scenario_give_the_same_estimates(tmp_path):
    """A short warm closed loop on the gravity-gradient scenario (its own [filter] tuning): the plain constructor
    and from_scenario write the same est.npz and det.npz."""
    from envisat_pose.pipelines.runs.closed_loop import run_closed_loop
    from envisat_pose.pipelines.runs.run_config import RunConfig

    small = {"duration_s": 3.0, "seed": 5, "warm_start": True, "workers": 1}
    resolved = RunConfig.from_scenario("gravity-gradient", overrides={**small, "image.resolution_px": 64})
    plain = RunConfig(scenario="gravity-gradient", weights=resolved.weights, image=resolved.image, **small)
    from envisat_pose.filtering.estimator import FilterConfig
    from envisat_pose.pipelines.tracking.tracker_config import TRACKER_FILTER

    assert plain.filter == resolved.filter != FilterConfig(**TRACKER_FILTER)  # the scenario's tuning, not the class's
    run_closed_loop(resolved, str(tmp_path / "a"), progress=False)
    run_closed_loop(plain, str(tmp_path / "b"), progress=False)
    for name in ("est.npz", "det.npz"):
        same_arrays(tmp_path / "a" / name, tmp_path / "b" / name, skip=("config_json",))


def test_library_errors_name_the_argument_and_the_verb_its_flag(tmp_path, capsys):
    from envisat_pose.config import InputError
    from envisat_pose.pipelines.runs.run_config import RunConfig

    with pytest.raises(InputError, match=r"^weights '.*nope.safetensors': no such file"):
        RunConfig.from_scenario("default", weights=str(tmp_path / "nope.safetensors"))
    assert main(["run", "--weights", str(tmp_path / "nope.safetensors"), "--out", str(tmp_path / "r")]) == 2
    assert "error: --weights " in capsys.readouterr().err
    from envisat_pose.pipelines.runs.frames import open_source

    with pytest.raises(InputError, match=r"^src '.*nothing': no such file or folder"):
        open_source(str(tmp_path / "nothing"), 1.0)
    assert main(["track", "--images", str(tmp_path / "nothing"), "--rate-hz", "1", "--out", str(tmp_path / "t")]) == 2
    assert "error: --images " in capsys.readouterr().err


def test_simulate_verb_and_library_agree(tmp_path):
    from envisat_pose.pipelines.campaigns.simulate import run_simulate
    from envisat_pose.pipelines.jobs import resolve_job

    a, b = str(tmp_path / "a.npz"), str(tmp_path / "b.npz")
    assert main(["simulate", "--scenario", "slow-tumble", "--duration-s", "6", "--seed", "3", "--out", a,
                 "--quiet"]) == 0
    run_simulate(resolve_job("simulate", "slow-tumble", duration_s=6.0, seed=3), b)
    same_arrays(a, b)


def test_estimate_verb_and_library_agree(tmp_path):
    from envisat_pose.pipelines.campaigns.estimate import EstimateConfig, run_estimate

    a, b = str(tmp_path / "a.npz"), str(tmp_path / "b.npz")
    assert main(["estimate", "--scenario", "pixels-1px", "--duration-s", "8", "--runs", "2", "--seed", "5",
                 "--out", a, "--quiet"]) == 0
    run_estimate(EstimateConfig.from_scenario("pixels-1px", runs=2, seed=5), b, scenario="pixels-1px",
                 duration_s=8.0)
    same_arrays(a, b)


def test_montecarlo_verb_and_library_agree(tmp_path):
    from envisat_pose.pipelines.campaigns.campaign import MonteCarloConfig, run_campaign
    from envisat_pose.pools import RunnerConfig

    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["montecarlo", "--scenario", "eclipse", "--runs", "2", "--duration-s", "20", "--block-runs", "1",
                 "--out", str(a), "--quiet"]) == 0
    cfg = MonteCarloConfig.from_scenario("eclipse", runs=2, duration_s=20.0, block_runs=1)
    run_campaign(cfg, str(b), RunnerConfig("local", 1))
    same_arrays(a / "campaign.npz", b / "campaign.npz")


@pytest.mark.slow  # ~20 s: two closed loops and a third interrupted
def test_run_verb_and_library_agree(tmp_path, monkeypatch):
    """`envisat run` and run_closed_loop(RunConfig.from_scenario(...)): the same arrays; the library stages its
    outputs too (an earlier run's outputs stay when a job fails)."""
    from envisat_pose.pipelines.runs.closed_loop import run_closed_loop
    from envisat_pose.pipelines.runs.run_config import RunConfig

    toml = tmp_path / "small.toml"
    toml.write_text("[image]\nresolution_px = 96\n")
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["run", "--duration-s", "4", "--seed", "2", "--warm-start", "--config", str(toml), "--out", str(a),
                 "--quiet"]) == 0
    cfg = RunConfig.from_scenario("default", str(toml), duration_s=4.0, seed=2, warm_start=True)
    run_closed_loop(cfg, str(b), progress=False)
    for name in ("truth.npz", "est.npz", "det.npz"):
        same_arrays(a / name, b / name)
    before = (b / "est.npz").read_bytes()

    def fail(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("envisat_pose.analysis.plots.plot_estimate", fail)  # after est.npz is written, staged
    with pytest.raises(KeyboardInterrupt):
        run_closed_loop(RunConfig.from_scenario("default", str(toml), duration_s=2.0, seed=3), str(b), progress=False)
    assert (b / "est.npz").read_bytes() == before and sorted(os.listdir(b)) == sorted(os.listdir(a))


@pytest.mark.slow  # ~14 s: 21 frames generated, tracked twice
def test_track_verb_and_library_agree(tmp_path):
    from envisat_pose.pipelines.runs.track import TrackConfig, track_frames

    gen = tmp_path / "gen"
    assert main(["generate", "--mode", "sequence", "--scenario", "default", "--num-images", "21", "--seed", "7",
                 "--resolution", "96", "--workers", "1", "--out", str(gen), "--quiet"]) == 0
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["track", "--images", str(gen), "--out", str(a), "--quiet"]) == 0
    track_frames(TrackConfig.from_scenario("default"), str(gen), out_dir=str(b), progress=False)
    for name in ("est.npz", "det.npz"):
        same_arrays(a / name, b / name)
