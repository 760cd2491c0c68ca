"""The library runs the job the verb runs (issues 39 and 54): the one way to build a job's config is its
constructor (`RunConfig(scenario=NAME, runs=4)` is the job of `envisat run --scenario NAME --runs 4`), and
pipelines/jobs.py's resolve_job reads the constructor's arguments from a file and flags, as the verbs do. For
every verb with a pipeline (simulate, estimate, montecarlo, run, track) the verb and the Python call on the same
inputs and seed write the same arrays (NaN where NaN). Small jobs: seconds of simulated time, a few runs, small
frames."""

import dataclasses
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
    from envisat_pose.pipelines.jobs import resolve_job

    q = named_scenarios.scenario_tables("default")["filter"]
    run = resolve_job("run", "default", overrides={"tracker.roi.enabled": False}, duration_s=3.0)
    assert run.duration_s == 3.0 and not run.tracker.roi.enabled and run.weights and run.image.sun_dir is not None
    assert all(getattr(run.filter, k) == pytest.approx(v) for k, v in q.items() if not isinstance(v, dict))
    track = resolve_job("track", "gravity-gradient", rate_hz=2.0)
    assert track.gravity_gradient and track.rate_hz == 2.0 and track.orbit is not None and track.weights
    mc = resolve_job("montecarlo", "eclipse", runs=2)
    assert mc.measurement.outages_s and mc.runs == 2
    est = resolve_job("estimate", "pixels-1px", overrides={"measurement.sigma_px": 2.0})
    assert est.scenario == "pixels-1px" and est.measurement.kind == "pixels" and est.measurement.sigma_px == 2.0
    assert resolve_job("estimate", None).scenario is None  # a truth file's job: no scenario, the classes' defaults
    assert resolve_job("simulate", "close-25m", seed=4).relative.rho0_C_m == (0.0, 25.0, 0.0)


def scenario_names():
    from envisat_pose import named_scenarios

    return named_scenarios.names()


def job_configs():
    """{kind: the config class of a job with a scenario}."""
    from envisat_pose.pipelines.campaigns.campaign_config import MonteCarloConfig
    from envisat_pose.pipelines.campaigns.estimate import EstimateConfig
    from envisat_pose.pipelines.runs.run_config import RunConfig
    from envisat_pose.pipelines.runs.track import TrackConfig

    return {"run": RunConfig, "track": TrackConfig, "estimate": EstimateConfig, "montecarlo": MonteCarloConfig}


@pytest.mark.parametrize("name", scenario_names())
def test_the_plain_constructor_with_a_scenario_is_the_scenarios_job(name):
    """Cfg(scenario=NAME) is exactly the job resolve_job(KIND, NAME) builds, for every job with a scenario: the
    gravity-gradient switch, the orbit and the filter's tuning of track; the duration, rate, filter, workers,
    shipped weights, image fields and sun of run; the tables of estimate; the duration, tables and eclipse
    outages of montecarlo (the plain constructor once took only part of them)."""
    from envisat_pose.config import to_dict
    from envisat_pose.pipelines.jobs import resolve_job

    for kind, cls in job_configs().items():
        plain, resolved = cls(scenario=name), resolve_job(kind, name)
        assert plain == resolved and to_dict(plain) == to_dict(resolved), kind


@pytest.mark.parametrize("name", scenario_names())
def test_a_job_replaced_with_another_scenario_is_that_scenarios_job(name):
    """dataclasses.replace(Cfg(scenario=A), scenario=B) is Cfg(scenario=B): what A filled in (duration, rate,
    tables, orbit, the gravity-gradient switch, the sun, the eclipse outages) is filled in again from B (it stayed
    A's: an eclipse campaign without its eclipse, a gravity-gradient track without the torque); what a user gave
    stays, and a config replaced without a new scenario keeps what it holds."""
    for kind, cls in job_configs().items():
        for a in ("default", "gravity-gradient", "eclipse"):
            replaced = dataclasses.replace(cls(scenario=a), scenario=name)
            assert replaced == cls(scenario=name), (kind, a)
        assert dataclasses.replace(cls(scenario=name), scenario=name) == cls(scenario=name), kind
    given = dataclasses.replace(job_configs()["montecarlo"](scenario="default", duration_s=60.0), scenario=name)
    assert given.duration_s == 60.0
    track = dataclasses.replace(job_configs()["track"](scenario="default", gravity_gradient=True), scenario=name)
    assert track.gravity_gradient
    three = job_configs()["montecarlo"](scenario="paper-3markers-0.02").measurement  # a table taken over:
    assert three.max_markers == 3  # a copy of it gives it
    assert job_configs()["montecarlo"](scenario=name, measurement=dataclasses.replace(three)).measurement == three


def test_a_runs_sun_given_equal_to_another_scenarios_stays_given():
    """An image given with its sun (the default scenario's, copied from a run's config) to a run of another
    scenario keeps it (it was taken for the default scenario's sun a run had put there, and replaced by the
    eclipse's); the sun a run finished its image with is the new scenario's after a replace."""
    from envisat_pose.datagen.generate_config import GenerateConfig
    from envisat_pose.pipelines.runs.run_config import RunConfig, scenario_sun

    sun = scenario_sun("default")
    image = GenerateConfig(mode="sequence", num_images=1, shard_size=1, write_mask=False, write_depth=False,
                           sun_dir=sun)
    assert RunConfig(scenario="eclipse", duration_s=20.0, image=image).image.sun_dir == sun
    replaced = dataclasses.replace(RunConfig(scenario="default", duration_s=20.0), scenario="eclipse")
    assert replaced.image.sun_dir == scenario_sun("eclipse") != sun


def test_a_campaign_replaced_with_a_longer_duration_has_that_truths_eclipse_outages():
    """The eclipse outages a campaign filled in follow its truth: dataclasses.replace with another duration (or
    seed) takes them along the new truth (they stayed the first 3600 s's: the second shadow was measured through),
    as the constructor does; a measurement given stays as it is."""
    mc = job_configs()["montecarlo"]
    longer = dataclasses.replace(mc(scenario="eclipse"), duration_s=9000.0)
    assert longer.measurement == mc(scenario="eclipse", duration_s=9000.0).measurement
    assert len(longer.measurement.outages_s) == 2
    assert dataclasses.replace(longer, seed=3) == mc(scenario="eclipse", duration_s=9000.0, seed=3)
    given = dataclasses.replace(mc(scenario="eclipse").measurement)  # a copy: given
    assert dataclasses.replace(mc(scenario="eclipse", measurement=given), duration_s=9000.0).measurement == given


def test_tracker_from_scenario_takes_the_track_jobs_scenario_parts():
    """Tracker.from_scenario (a tracker, not a config: below the track job, so it cannot build a TrackConfig)
    takes what TrackConfig(scenario=NAME) takes from each scenario: the filter, the orbit, the gravity gradient."""
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.pipelines.tracking.build import tracker_filter

    for name in scenario_names():
        job, truth = job_configs()["track"](scenario=name), scenario_config(name)
        assert job.filter == tracker_filter(None, name), name
        assert job.orbit == truth.orbit and job.gravity_gradient == truth.target.gravity_gradient, name


def parsed(verb: list[str]):
    from envisat_pose.app.cli import build_parser

    return build_parser().parse_args(verb + ["--out", "unused"])


def test_the_constructor_is_the_verbs_job_for_the_same_flags():
    """`envisat KIND --scenario NAME --runs 4 ...` runs Cfg(scenario=NAME, runs=4, ...): the config each verb
    resolves from its flags equals the constructor's with the same values (== and to_dict), for run, track,
    estimate and montecarlo; the run's workers, shipped weights, image fields and sun, the campaign's eclipse
    outages included."""
    from envisat_pose.app import estimate, montecarlo, run
    from envisat_pose.config import to_dict
    from envisat_pose.pipelines.jobs import resolve_job
    from envisat_pose.pipelines.runs.run_config import RUN_PROCESS_BYTES
    from envisat_pose.pools import default_processes

    cfgs = job_configs()
    pairs = [
        (run.resolve_config(parsed(["run", "--scenario", "gravity-gradient", "--runs", "4", "--seed", "3",
                                    "--duration-s", "5"])),
         cfgs["run"](scenario="gravity-gradient", runs=4, seed=3, duration_s=5.0)),
        (resolve_job("track", "slow-tumble", None, rate_hz=2.0, weights=None),  # what `envisat track` resolves
         cfgs["track"](scenario="slow-tumble", rate_hz=2.0)),
        (estimate.resolve_config(parsed(["estimate", "--scenario", "pixels-1px", "--runs", "4", "--seed", "3"])),
         cfgs["estimate"](scenario="pixels-1px", runs=4, seed=3)),
        (montecarlo.resolve_config(parsed(["montecarlo", "--scenario", "eclipse", "--runs", "4", "--seed", "3",
                                           "--duration-s", "3000"])),
         cfgs["montecarlo"](scenario="eclipse", runs=4, seed=3, duration_s=3000.0)),
    ]
    for verb, plain in pairs:
        assert verb == plain and to_dict(verb) == to_dict(plain), type(plain).__name__
    run_cfg = pairs[0][1]
    assert run_cfg.workers == default_processes(4, RUN_PROCESS_BYTES) and os.path.isfile(run_cfg.weights)
    assert run_cfg.image.num_images == 6 and run_cfg.image.seed == 3 and run_cfg.image.sun_dir is not None
    assert pairs[3][1].measurement.outages_s  # the eclipse scenario's shadow, once


def test_every_job_config_is_validated_when_built(tmp_path):
    """A constructor (and dataclasses.replace) refuses what from_dict refuses, naming the field; a config file's
    nested table is named under its table."""
    from envisat_pose.config import ConfigError, InputError
    from envisat_pose.filtering.estimator import FilterConfig
    from envisat_pose.pipelines.jobs import resolve_job

    cfgs = job_configs()
    with pytest.raises(ConfigError, match=r"^runs = 0"):
        cfgs["run"](runs=0)
    with pytest.raises(ConfigError, match=r"^threads = 0"):
        dataclasses.replace(cfgs["track"](), threads=0)
    with pytest.raises(ConfigError, match=r"^runs = 0"):
        cfgs["estimate"](scenario="default", runs=0)
    with pytest.raises(ConfigError, match=r"^block_runs = 0"):
        cfgs["montecarlo"](block_runs=0)
    with pytest.raises(ConfigError, match=r"^p0_sigma = \[-1"):
        FilterConfig(p0_sigma=(-1.0, 0.01, 0.044, 1.7e-3))
    with pytest.raises(ConfigError, match=r"^filter\.p0_sigma = \[-1"):
        resolve_job("estimate", "default", overrides={"filter.p0_sigma": [-1.0, 0.01, 0.044, 1.7e-3]})
    with pytest.raises(ConfigError, match=r"^tracker\.acquire\.frames = 2"):
        resolve_job("run", "default", overrides={"tracker.acquire.frames": 2})
    with pytest.raises(ConfigError, match=r"^scenario = 'nope'"):
        cfgs["run"](scenario="nope")
    with pytest.raises(InputError, match=r"^weights '.*nope.safetensors': no such file"):
        cfgs["track"](weights=str(tmp_path / "nope.safetensors"))


@pytest.mark.parametrize("kind", ["run", "track", "estimate", "montecarlo"])
def test_from_scenario_is_deprecated_and_still_the_same_job(kind):
    """Cfg.from_scenario (one release): a DeprecationWarning naming the one way, and the job resolve_job builds."""
    from envisat_pose.pipelines.jobs import resolve_job

    cls = job_configs()[kind]
    fields = {"rate_hz": 2.0} if kind == "track" else {"runs": 2}
    with pytest.warns(DeprecationWarning, match=rf"{cls.__name__}\.from_scenario is deprecated .* use "
                                                 rf"{cls.__name__}\(scenario=NAME, \.\.\.\)"):
        old = cls.from_scenario("gravity-gradient", None, {"filter.adaptive_q": True}, **fields)
    assert old == resolve_job(kind, "gravity-gradient", None, {"filter.adaptive_q": True}, **fields)
    assert old.filter.adaptive_q and old.scenario == "gravity-gradient"


def test_the_plain_constructor_and_resolve_job_give_the_same_estimates(tmp_path):
    """A short warm closed loop on the gravity-gradient scenario (its own [filter] tuning): the plain constructor
    and resolve_job write the same est.npz and det.npz."""
    from envisat_pose.pipelines.jobs import resolve_job
    from envisat_pose.pipelines.runs.closed_loop import run_closed_loop
    from envisat_pose.pipelines.runs.run_config import RunConfig

    small = {"duration_s": 3.0, "seed": 5, "warm_start": True, "workers": 1}
    resolved = resolve_job("run", "gravity-gradient", overrides={**small, "image.resolution_px": 64})
    plain = RunConfig(scenario="gravity-gradient", image=resolved.image, **small)
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
        RunConfig(weights=str(tmp_path / "nope.safetensors"))
    assert main(["run", "--weights", str(tmp_path / "nope.safetensors"), "--out", str(tmp_path / "r")]) == 2
    assert "error: --weights " in capsys.readouterr().err
    from envisat_pose.pipelines.runs.frames import open_source

    with pytest.raises(InputError, match=r"^source '.*nothing': no such file or folder"):
        open_source(str(tmp_path / "nothing"), 1.0)
    assert main(["track", "--images", str(tmp_path / "nothing"), "--rate-hz", "1", "--out", str(tmp_path / "t")]) == 2
    assert "error: --images " in capsys.readouterr().err
    # track_frames and adapt take the frames as `source` (once named `src` in their errors, open_source's old name)
    import cv2
    import numpy as np

    from envisat_pose.pipelines.adaptation.adapt import AdaptConfig, adapt
    from envisat_pose.pipelines.runs.track import TrackConfig, track_frames

    cfg = TrackConfig(scenario="default", rate_hz=1.0)
    with pytest.raises(InputError, match=r"^source '.*nothing': no such file or folder"):
        track_frames(cfg, str(tmp_path / "nothing"), out_dir=str(tmp_path / "t"))
    with pytest.raises(InputError, match=r"^source '.*nothing': no such file or folder"):
        adapt(AdaptConfig(), str(tmp_path / "nothing"), str(tmp_path / "a"))
    (tmp_path / "two").mkdir()
    for i in range(2):
        cv2.imwrite(str(tmp_path / "two" / f"img_{i:04d}.png"), np.zeros((64, 64), np.uint8))
    with pytest.raises(InputError, match=r"^source '.*two': 2 frame\(s\); the tracker's cold start needs"):
        track_frames(cfg, str(tmp_path / "two"), out_dir=str(tmp_path / "t"))


def test_simulate_verb_and_library_agree(tmp_path):
    from envisat_pose.pipelines.campaigns.simulate import run_simulate
    from envisat_pose.pipelines.jobs import resolve_job

    a, b = str(tmp_path / "a.npz"), str(tmp_path / "b.npz")
    assert main(["simulate", "--scenario", "slow-tumble", "--duration-s", "6", "--seed", "3", "--out", a,
                 "--quiet"]) == 0
    run_simulate(resolve_job("simulate", "slow-tumble", duration_s=6.0, seed=3), b)  # its scenario recorded
    same_arrays(a, b)


def test_estimate_verb_and_library_agree(tmp_path):
    from envisat_pose.pipelines.campaigns.estimate import EstimateConfig, run_estimate

    a, b = str(tmp_path / "a.npz"), str(tmp_path / "b.npz")
    assert main(["estimate", "--scenario", "pixels-1px", "--duration-s", "8", "--runs", "2", "--seed", "5",
                 "--out", a, "--quiet"]) == 0
    run_estimate(EstimateConfig(scenario="pixels-1px", runs=2, seed=5), b, duration_s=8.0)  # its scenario's truth
    same_arrays(a, b)


def test_montecarlo_verb_and_library_agree(tmp_path):
    from envisat_pose.pipelines.campaigns.campaign import MonteCarloConfig, run_campaign
    from envisat_pose.pools import RunnerConfig

    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["montecarlo", "--scenario", "eclipse", "--runs", "2", "--duration-s", "20", "--block-runs", "1",
                 "--out", str(a), "--quiet"]) == 0
    cfg = MonteCarloConfig(scenario="eclipse", runs=2, duration_s=20.0, block_runs=1)
    run_campaign(cfg, str(b), RunnerConfig("local", 1))
    same_arrays(a / "campaign.npz", b / "campaign.npz")


@pytest.mark.slow  # ~20 s: two closed loops and a third interrupted
def test_run_verb_and_library_agree(tmp_path, monkeypatch):
    """`envisat run` and run_closed_loop(resolve_job("run", ...)): the same arrays; the library stages its
    outputs too (an earlier run's outputs stay when a job fails)."""
    from envisat_pose.pipelines.jobs import resolve_job
    from envisat_pose.pipelines.runs.closed_loop import run_closed_loop

    toml = tmp_path / "small.toml"
    toml.write_text("[image]\nresolution_px = 96\n")
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["run", "--duration-s", "4", "--seed", "2", "--warm-start", "--config", str(toml), "--out", str(a),
                 "--quiet"]) == 0
    cfg = resolve_job("run", "default", str(toml), duration_s=4.0, seed=2, warm_start=True)
    run_closed_loop(cfg, str(b), progress=False)
    for name in ("truth.npz", "est.npz", "det.npz"):
        same_arrays(a / name, b / name)
    before = (b / "est.npz").read_bytes()

    def fail(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("envisat_pose.analysis.plots.plot_estimate", fail)  # after est.npz is written, staged
    with pytest.raises(KeyboardInterrupt):
        run_closed_loop(resolve_job("run", "default", str(toml), duration_s=2.0, seed=3), str(b), progress=False)
    assert (b / "est.npz").read_bytes() == before and sorted(os.listdir(b)) == sorted(os.listdir(a))


@pytest.mark.slow  # ~14 s: 21 frames generated, tracked twice
def test_track_verb_and_library_agree(tmp_path):
    from envisat_pose.pipelines.runs.track import TrackConfig, track_frames

    gen = tmp_path / "gen"
    assert main(["generate", "--mode", "sequence", "--scenario", "default", "--num-images", "21", "--seed", "7",
                 "--resolution", "96", "--workers", "1", "--out", str(gen), "--quiet"]) == 0
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["track", "--images", str(gen), "--out", str(a), "--quiet"]) == 0
    track_frames(TrackConfig(scenario="default"), str(gen), out_dir=str(b), progress=False)
    for name in ("est.npz", "det.npz"):
        same_arrays(a / name, b / name)


@pytest.mark.parametrize("kind", ["run", "track", "estimate", "montecarlo"])
def test_a_resolved_job_replaced_with_another_scenario_is_that_scenarios_job(kind):
    """resolve_job marks what the scenario alone set, as the constructor marks what it fills in: replaced with
    another scenario it is that scenario's job; what a file or a flag set stays."""
    from envisat_pose.pipelines.jobs import resolve_job

    cls = job_configs()[kind]
    for a, b in (("default", "eclipse"), ("eclipse", "gravity-gradient"), ("gravity-gradient", "paper-all-0.2")):
        assert dataclasses.replace(resolve_job(kind, a), scenario=b) == cls(scenario=b), (kind, a, b)
    flagged = resolve_job(kind, "default", overrides={"filter.kappa": 0.5})
    assert dataclasses.replace(flagged, scenario="eclipse").filter.kappa == 0.5


def test_a_config_file_naming_another_scenario_is_said(tmp_path):
    """A file's `scenario` key that the job does not run (a --scenario over a run's written config) is warned of
    in one line naming both; the file's other keys apply. A file naming the job's own scenario, or none, is not."""
    import warnings

    from envisat_pose.pipelines.jobs import resolve_job

    other = tmp_path / "other.toml"
    other.write_text('scenario = "slow-tumble"\nduration_s = 7.0\n')
    said = r"other.toml: its scenario = 'slow-tumble' is not this job's; the job runs scenario 'default'"
    with pytest.warns(UserWarning, match=said):
        cfg = resolve_job("run", "default", str(other))
    assert cfg.scenario == "default" and cfg.duration_s == 7.0
    named = tmp_path / "named.toml"
    named.write_text('scenario = "slow-tumble"\n')
    with pytest.warns(UserWarning, match="takes no named scenario"):  # a truth file's estimate
        assert resolve_job("estimate", None, str(named)).scenario is None
    same = tmp_path / "same.toml"
    same.write_text('scenario = "slow-tumble"\nduration_s = 7.0\n')
    none = tmp_path / "none.toml"
    none.write_text("duration_s = 7.0\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert resolve_job("run", "slow-tumble", str(same)).duration_s == 7.0
        assert resolve_job("montecarlo", "default", str(none), runs=2).duration_s == 7.0


def test_the_layers_merge_key_by_key_and_mark_only_what_the_scenario_alone_set(tmp_path):
    """resolve_job's layers against the scenario files read here: a file's partial [filter] table keeps the
    scenario's other keys; a file's `scenario` key does not replace the one named; a campaign keeps its scenario's
    [measurement] table; a duration from a file stays through a replace with another scenario, and flags not given
    (None, as the verbs pass them) leave the scenario's duration marked as its own, so the replace takes the new
    scenario's."""
    from envisat_pose import named_scenarios
    from envisat_pose.pipelines.jobs import resolve_job

    default, eclipse = (named_scenarios.scenario_tables(n) for n in ("default", "eclipse"))
    path = tmp_path / "job.toml"
    path.write_text('scenario = "eclipse"\nduration_s = 7.0\n\n[filter]\np0_sigma = [2.0, 0.02, 0.05, 2e-3]\n')
    with pytest.warns(UserWarning, match="'eclipse' is not this job's"):
        run = resolve_job("run", "default", str(path))
    assert run.scenario == "default" and run.duration_s == 7.0
    assert list(run.filter.p0_sigma) == [2.0, 0.02, 0.05, 2e-3]
    assert list(run.filter.q_sigma) == pytest.approx(default["filter"]["q_sigma"])  # the scenario's, kept
    assert dataclasses.replace(run, scenario="eclipse").duration_s == 7.0  # the file's
    unflagged = resolve_job("run", "default", overrides={"duration_s": None, "runs": None}, seed=None)
    assert dataclasses.replace(unflagged, scenario="eclipse").duration_s == eclipse["duration_s"] != 7.0
    pixels = named_scenarios.scenario_tables("pixels-1px")["measurement"]
    mc = resolve_job("montecarlo", "pixels-1px")
    assert (mc.measurement.kind, mc.measurement.sigma_px) == (pixels["kind"], pixels["sigma_px"]) == ("pixels", 1.0)


def test_a_runs_full_frame_interval_is_validated_when_built():
    """full_frame_every = 0 would divide by zero at the loop's first windowed frame, after the truth is
    simulated: refused when the config is built, naming the field."""
    from envisat_pose.config import ConfigError
    from envisat_pose.pipelines.runs.run_config import RunConfig

    with pytest.raises(ConfigError, match=r"^full_frame_every = 0"):
        RunConfig(scenario="default", full_frame_every=0)
