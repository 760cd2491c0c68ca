"""What a verb refuses or does, its Python function refuses or does too, in a line naming the Python argument: an
estimate of a truth file and a scenario at once, a training device torch does not know, adapt's learning rate
without its fine-tune, a rate-sweep scenario given to run_campaign (the verb runs one campaign per rate), and a
generated folder tracked under another scenario than its own (the verb takes the folder's)."""

import os
import warnings

import pytest

from envisat_pose.config import ConfigError, InputError


def test_run_estimate_refuses_a_truth_file_and_a_scenario_at_once(tmp_path):
    """`envisat estimate` takes --truth or --scenario (argparse's exclusive group); the call read the file and added
    the scenario's eclipse outages along it."""
    from envisat_pose import EstimateConfig, ScenarioConfig, run_estimate, run_simulate

    truth = str(tmp_path / "t.npz")
    run_simulate(ScenarioConfig(duration_s=5.0), truth)
    with pytest.raises(InputError, match="^truth_path and scenario: give one of them"):
        run_estimate(EstimateConfig(), str(tmp_path / "e.npz"), truth_path=truth, scenario="eclipse")
    assert not os.path.exists(tmp_path / "e.npz")


@pytest.mark.parametrize("device", ["gpu", "cuda0", 1])
def test_train_detector_names_a_device_it_cannot_use(device, tmp_path):
    """The verb's --device is cpu or cuda; the call gave torch's own RuntimeError listing every device type."""
    from envisat_pose import TrainConfig, train_detector

    with pytest.raises(InputError, match=f"^device {device!r}: expected 'cpu' or 'cuda'"):
        train_detector(TrainConfig(steps=1), str(tmp_path / "data"), str(tmp_path / "run"), device=device)


def test_train_detector_takes_a_numbered_cuda_device_past_the_check(tmp_path):
    from envisat_pose import TrainConfig, train_detector

    with pytest.raises(InputError) as err:  # the next check: the folder given is not a dataset
        train_detector(TrainConfig(steps=1), str(tmp_path / "data"), str(tmp_path / "run"), device="cuda:0")
    assert not str(err.value).startswith("device")


def test_adapt_names_the_fine_tune_setting_given_without_the_fine_tune():
    from envisat_pose.pipelines.adaptation.adapt import AdaptConfig

    with pytest.raises(ConfigError) as err:
        AdaptConfig(lr=1e-3)
    assert err.value.field == "lr" and str(err.value).startswith("lr = 0.001: expected the defaults")


def test_run_campaign_refuses_a_rate_sweep_and_run_sweep_runs_it(tmp_path):
    """`envisat montecarlo --scenario rate-sweep` runs one campaign per rate; run_campaign ran one at 1 Hz."""
    from envisat_pose import MonteCarloConfig, run_campaign
    from envisat_pose.pipelines.campaigns.sweep import run_sweep, sweep_for

    cfg = MonteCarloConfig(scenario="rate-sweep", runs=2, duration_s=20.0)
    with pytest.raises(ConfigError, match="^scenario = 'rate-sweep': expected a scenario of one rate.*run_sweep"):
        run_campaign(cfg, tmp_path / "one")
    assert not os.path.exists(tmp_path / "one")
    result = run_sweep(cfg, sweep_for(cfg, [1.0]), str(tmp_path / "sweep"))  # what the message names
    assert result["rates_hz"] == [1.0] and os.path.isfile(tmp_path / "sweep" / "rate-1hz" / "summary.json")


def test_a_generated_sequence_tracked_under_another_scenario_is_warned_of(tmp_path):
    """`envisat track --images SEQ` takes SEQ's own scenario; TrackConfig() is the default scenario's: said."""
    from envisat_pose import GenerateConfig, TrackConfig, run_generate
    from envisat_pose.pipelines.runs.track import prepare_frames

    seq = str(tmp_path / "seq")
    run_generate(GenerateConfig(mode="sequence", num_images=20, shard_size=20, resolution_px=64, seed=1,
                                sequence={"scenario": "slow-tumble"}), seq)
    with pytest.warns(UserWarning, match="frames of scenario 'slow-tumble', tracked with the orbit, dynamics and "
                      r"filter of scenario 'default' \(TrackConfig\(scenario='slow-tumble'\)"):
        prepare_frames(TrackConfig(), seq)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        prepare_frames(TrackConfig(scenario="slow-tumble"), seq)  # the frames' own, as the verb takes it


def test_run_estimate_without_a_truth_or_a_scenario_says_to_give_one(tmp_path):
    """It said `scenario = None: expected one of ...`, naming neither argument."""
    from envisat_pose import EstimateConfig, run_estimate

    with pytest.raises(InputError, match="^truth_path or scenario: give one"):
        run_estimate(EstimateConfig(runs=1), str(tmp_path / "e.npz"))
    assert not os.listdir(tmp_path)


def test_run_campaign_gives_its_workers_a_share_of_the_cores_for_linear_algebra(tmp_path, monkeypatch):
    """`envisat montecarlo --workers 4` gave each worker its BLAS thread share (OMP/OPENBLAS/MKL_NUM_THREADS);
    run_campaign(cfg, out, RunnerConfig("local", 4)) did not, so 4 workers each took every core."""
    import dataclasses

    from envisat_pose import MonteCarloConfig, RunnerConfig, resumable, run_campaign
    from envisat_pose.pools import BLAS_THREADS, thread_env

    seen, real = [], resumable.run_tasks

    def recorded(fn, tasks, cfg):
        seen.append(cfg.env)
        return real(fn, tasks, dataclasses.replace(cfg, backend="inline"))  # the same tasks, in this process

    monkeypatch.setattr(resumable, "run_tasks", recorded)
    cfg = MonteCarloConfig(runs=2, duration_s=20.0, settle_s=10.0)
    run_campaign(cfg, tmp_path / "a", RunnerConfig("local", 4))
    assert seen == [thread_env(4, BLAS_THREADS)]
    run_campaign(cfg, tmp_path / "b", RunnerConfig("local", 4, env={"OMP_NUM_THREADS": "3"}))  # the caller's kept
    assert seen[1]["OMP_NUM_THREADS"] == "3" and seen[1]["MKL_NUM_THREADS"] == thread_env(4, BLAS_THREADS)[
        "MKL_NUM_THREADS"]


@pytest.mark.parametrize("cfg", [None, {"steps": 3}, "config.toml"])
def test_train_detector_names_a_config_that_is_no_training_config(cfg, tmp_path):
    """None reached the data's check (its refusal named the data) and a dict failed once training began; both
    now one line naming cfg, nothing written."""
    from envisat_pose import train_detector

    run = tmp_path / "run"
    with pytest.raises(InputError, match=f"^cfg: expected a TrainConfig or a KeypointTrainConfig, got "
                                         f"{type(cfg).__name__}"):
        train_detector(cfg, str(tmp_path), str(run))
    assert not run.exists()


@pytest.mark.parametrize("kwargs, field", [({"workers": 0}, "workers"), ({"workers": 2.0}, "workers"),
                                           ({"scheduler": "127.0.0.1:1"}, "scheduler")])
def test_run_generate_refuses_what_the_verb_refuses_as_the_same_config_error(kwargs, field, tmp_path):
    """`envisat generate --workers 0` and `--scheduler` without `--backend dask` raised InputErrors of their own
    ('--workers 0: expected at least 1', '--scheduler needs --backend dask') where run_generate raised ConfigErrors
    worded otherwise; the verb now says the function's, naming the flag typed (tests/app/test_generate_cli.py)."""
    from envisat_pose import GenerateConfig, run_generate

    out = tmp_path / "ds"
    with pytest.raises(ConfigError) as err:
        run_generate(GenerateConfig(num_images=2, shard_size=1, resolution_px=64), str(out), **kwargs)
    assert err.value.field == field and err.value.value == kwargs[field]
    assert not out.exists()


def test_run_estimate_names_the_truth_file_it_cannot_read_by_its_argument(tmp_path, capsys):
    """run_estimate's error, and the verb's, said '/x/run.npz: no such file', naming neither truth_path nor --truth."""
    from envisat_pose import EstimateConfig, run_estimate
    from envisat_pose.app.cli import main

    missing, folder = str(tmp_path / "run.npz"), str(tmp_path)
    with pytest.raises(InputError, match=f"^truth_path {missing!r}: no such file$"):
        run_estimate(EstimateConfig(runs=1), str(tmp_path / "e.npz"), truth_path=missing)
    with pytest.raises(InputError, match=f"^truth_path {folder!r}: is a folder"):
        run_estimate(EstimateConfig(runs=1), str(tmp_path / "e.npz"), truth_path=folder)
    assert main(["estimate", "--truth", missing, "--out", str(tmp_path / "e.npz"), "--quiet"]) == 2
    assert capsys.readouterr().err == f"envisat estimate: error: --truth {missing!r}: no such file\n"


def test_train_detector_refuses_loader_workers_for_an_online_run(tmp_path):
    """`envisat train --online --workers 4` is refused (its frames come from --render-workers); train_detector
    took workers=4 with online= and dropped it without a word."""
    from envisat_pose import GenerateConfig, TrainConfig, train_detector
    from envisat_pose.pipelines.detector.train import OnlineConfig

    with pytest.raises(InputError, match="^workers = 4: the DataLoader processes reading data_dirs' shards; an "
                                         r"online run's frames come from its renderer processes \(online.workers\)"):
        train_detector(TrainConfig(steps=1), [], str(tmp_path / "run"), workers=4,
                       online=OnlineConfig(GenerateConfig(resolution_px=64)))
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("kwargs, field", [({"limit": 0}, "limit"), ({"limit": -1}, "limit"),
                                           ({"weights": "nope.safetensors"}, "weights")])
def test_fit_face_cue_checks_its_weights_and_limit_as_the_verb_does(kwargs, field, tmp_path):
    """`envisat calibrate --face-cue --limit 0` or a missing --weights is refused before any work; fit_face_cue
    read every frame first (limit 0 or -1: none, then a fit of nothing; a missing weights file: failed writing)."""
    from envisat_pose.pipelines.detector.calibrate import fit_face_cue

    args = {"weights": "", "data": [str(tmp_path / "not-read")], "held_out": [], "out": str(tmp_path / "w.safetensors")}
    with pytest.raises((ConfigError, InputError)) as err:
        fit_face_cue(**{**args, **kwargs})
    assert str(err.value).startswith(f"{field} ")
    assert not (tmp_path / "w.safetensors").exists()


@pytest.mark.parametrize("scenario", ["default", "gravity-gradient"])
def test_adapts_track_table_as_a_dict_lies_over_its_scenario_as_the_verbs_file_does(tmp_path, scenario):
    """`envisat adapt --config FILE` lays the file's [filter] over the track job of its scenario (resolve_job);
    AdaptConfig(track={...}) gave the same table to TrackConfig by from_dict, which built it over FilterConfig's
    class defaults instead (adaptive_r off, gate_lockout_steps 10^6, ...), where TrackConfig(filter={...})
    itself lays it over the scenario's. Now the three are one config."""
    from envisat_pose.config import from_dict, to_dict
    from envisat_pose.pipelines.adaptation.adapt import AdaptConfig
    from envisat_pose.pipelines.jobs import resolve_job
    from envisat_pose.pipelines.runs.track import TrackConfig

    path = tmp_path / "track.toml"
    path.write_text("[filter]\nq_sigma = [1e-7, 1e-7, 1e-8, 1e-9]\n\n[orbit]\ne = 0.002\n")
    verb = to_dict(resolve_job("track", scenario, str(path)))  # what app/adapt.py builds from --config
    table = {"scenario": scenario, "filter": {"q_sigma": [1e-7, 1e-7, 1e-8, 1e-9]}, "orbit": {"e": 0.002}}
    assert to_dict(AdaptConfig(track=table).track) == verb
    assert to_dict(TrackConfig(**table)) == verb
    assert to_dict(from_dict(AdaptConfig, {"track": table}).track) == verb  # a file's [track] table, read
    with pytest.raises(ConfigError, match=r"^track\.filter\.q_sigma"):  # a bad key still named where it sits
        AdaptConfig(track={"filter": {"q_sigma": "fast"}})
