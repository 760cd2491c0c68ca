"""The training user's path (issue 41): budgets that mean what they say, Ctrl-C then resume, resume refusing other
data or another model with the difference spelled out, `--out` on or under a file, the record that reproduces
the command, a plain script without a `__main__` guard, configs validated when built."""

import json
import os
import shlex
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from envisat_pose.app.cli import main
from envisat_pose.config import ConfigError, InputError, from_dict
from envisat_pose.perception.data import DataConfig
from envisat_pose.perception.model import ModelConfig
from envisat_pose.perception.train import TrainConfig, train

SMALL_TOML = """steps = 100000
batch_size = 2
warmup_steps = 5
checkpoint_every = 100000
[model]
input_px = 128
width = 16
depth = 2
stem_width = 8
[data]
input_px = 128
"""


def small(steps=4, **kw):
    return TrainConfig(steps=steps, batch_size=2, warmup_steps=2, checkpoint_every=10 ** 6,
                       model=ModelConfig(input_px=128, width=16, depth=2, stem_width=8),
                       data=DataConfig(input_px=128), **kw)


def one_line_error(capsys, code) -> str:
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    return err


def test_configs_are_validated_when_built():
    with pytest.raises(ConfigError, match="steps"):
        TrainConfig(steps=0)
    with pytest.raises(ConfigError, match="time_budget_s"):
        TrainConfig(time_budget_s=0.0)


def test_a_zero_budget_is_refused_with_a_hint(tiny_dataset, tmp_path, capsys):
    run = tmp_path / "run"
    err = one_line_error(capsys, main(["train", "--data", tiny_dataset, "--out", str(run), "--time-budget-s", "0",
                                       "--quiet"]))
    assert "--time-budget-s" in err and "leave it out" in err
    assert not run.exists()


class SlowClock:
    """Every reading 30 s after the last: the first batch arrives long after any small budget."""

    def __init__(self):
        self.t = 0.0

    def __call__(self):
        self.t += 30.0
        return self.t


def test_a_budget_too_short_for_one_step_is_refused_and_leaves_nothing(tiny_dataset, tmp_path):
    run = tmp_path / "sub" / "run"
    with pytest.raises(InputError, match="too short for one step"):
        train(small(time_budget_s=40.0), tiny_dataset, str(run), progress=False, clock=SlowClock())
    assert not run.exists()


def test_a_resumed_run_whose_budget_is_all_but_spent_has_nothing_to_do(tiny_dataset, tmp_path):
    """A run resumed under its own budget with less of it left than a step needs: nothing to do, its budget
    spent (it was once refused as 'time_budget_s = 90: too short for one step', a flag the user never typed); a
    new budget too short for a step is still refused."""
    run = tmp_path / "run"
    first = train(small(2, time_budget_s=40.0), tiny_dataset, str(run), progress=False)
    assert first["step"] == 2
    end = train(small(4, time_budget_s=40.0), tiny_dataset, str(run), resume=True, progress=False,
                clock=SlowClock())
    assert end["stopped_by"] == "nothing_to_do" and end["why"] == "budget_spent" and end["step"] == 2
    with pytest.raises(InputError, match="too short for one step"):
        train(small(4, time_budget_s=41.0), tiny_dataset, str(run), resume=True, progress=False, clock=SlowClock())


def resumed_with_left(run, data, monkeypatch, left: float):
    """A 2-step run trained into run, its state.json set to left x its min_leg_s of budget left, then resumed for 4
    steps with the batch sources' starts counted: (the state written, the resume's end line, the starts)."""
    from envisat_pose.perception import train as train_module

    train(small(2, time_budget_s=40.0), data, str(run), progress=False)
    state = json.loads((run / "state.json").read_text())
    state["time_s"] = state["budget_end_s"] - left * state["min_leg_s"]
    (run / "state.json").write_text(json.dumps(state))
    started = []
    real = train_module.shard_batches
    monkeypatch.setattr(train_module, "shard_batches", lambda *a: started.append(1) or real(*a))
    end = train(small(4, time_budget_s=40.0), data, str(run), resume=True, progress=False)
    return state, end, started


def test_a_budget_left_below_the_last_legs_start_up_starts_nothing(tiny_dataset, tmp_path, monkeypatch):
    """state.json records the least of the budget a resume trains a step in (min_leg_s: the leg's wait for its
    first batch and the reserve before a step). A resume with less left than that says nothing to do before it
    starts any batch source (the renderers of an online run once started for ~3 s to train nothing); with more
    left it trains."""
    run = tmp_path / "run"
    state, end, started = resumed_with_left(run, tiny_dataset, monkeypatch, 0.9)
    assert state["min_leg_s"] >= 1.5  # at least the checkpoint's first guess (0.5 s) and the shutdown's 1 s
    assert (end["stopped_by"], end["why"], end["step"], started) == ("nothing_to_do", "budget_spent", 2, [])
    with pytest.raises(InputError, match="too short for one step"):  # a new budget shorter than that: refused
        train(small(4, time_budget_s=0.5 * state["min_leg_s"]), tiny_dataset, str(run), resume=True, progress=False)
    assert started == []
    state["time_s"] = 0.0  # the whole budget left: the same resume trains on
    (run / "state.json").write_text(json.dumps(state))
    end = train(small(4, time_budget_s=40.0), tiny_dataset, str(run), resume=True, progress=False)
    assert end["step"] == 4 and started == [1]


def test_a_resume_whose_start_up_may_outlast_what_is_left_starts_nothing_and_says_why(tiny_dataset, tmp_path,
                                                                                     monkeypatch):
    """A resume with 1.5 x the last leg's min_leg_s left: once enough by the record, but a leg's start-up varies
    (an online run's renderers once started slower than the leg before, used what was left and trained no step).
    A resume is now given a step only with LEG_START_MARGIN (2) x min_leg_s left: this one starts no batch
    source, and its end line says what was left and what a resume needs, as the verb's one line does."""
    state, end, started = resumed_with_left(tmp_path / "run", tiny_dataset, monkeypatch, 1.5)
    assert (end["stopped_by"], end["why"], end["step"], started) == ("nothing_to_do", "budget_spent", 2, [])
    from envisat_pose.perception.train_run import LEG_START_MARGIN
    from envisat_pose.pipelines.detector.train_records import nothing_to_do_line

    assert LEG_START_MARGIN == 2.0
    assert end["left_s"] == pytest.approx(1.5 * state["min_leg_s"], abs=2e-3)
    assert end["need_s"] == pytest.approx(2.0 * state["min_leg_s"], abs=2e-3)
    line = nothing_to_do_line("out/run", {**end, "left_s": 3.04, "need_s": 4.0}, 40.0)
    assert line == ("nothing to do: out/run is at step 2, its budget spent (3.0 s of it left, a resume needs 4.0 s: "
                    "its last leg's start-up and a step's reserve, with a margin); give --time-budget-s S (S above "
                    "4.0, other than its 40) to train S seconds more")
    assert nothing_to_do_line("r", {"step": 7, "why": "steps_reached"}, None) == \
        "nothing to do: r is at step 7, its steps reached; give --steps above 7 to go further"


def test_the_end_line_says_a_slow_legs_rate_and_no_rate_for_no_step(tiny_dataset, tmp_path, monkeypatch, capsys):
    """A resumed leg of one step at 0.49 samples/s (its first step pays torch's start-up: measured on a loaded
    2-core machine, `train --resume --steps 3` after 2 steps) was printed as '0 samples/s'; the line says 0.49, a
    fast run's whole number, and no rate at all for a call that trained no step."""
    from envisat_pose.app import train as train_verb

    end = {"kind": "end", "step": 3, "steps_run": 1, "loss": 5.6284, "samples_s": 0.49, "workers": 0,
           "stopped_by": "steps"}
    for given, said in ((end, "0.49 samples/s with 0 workers"), ({**end, "samples_s": 0.004}, "under 0.01 samples/s"),
                        ({**end, "samples_s": 1234.4, "steps_run": 900}, "1234 samples/s"),
                        ({**end, "steps_run": 0, "samples_s": 0.0},
                         "mean loss 5.6284 over the last epoch's steps, with 0 workers")):
        monkeypatch.setattr(train_verb, "train_detector", lambda *a, given=given, **k: given)
        assert main(["train", "--data", tiny_dataset, "--out", str(tmp_path / "run"), "--quiet"]) == 0
        out = capsys.readouterr().out
        assert said in out and " 0 samples/s" not in out and out.startswith("trained to step 3"), out
    assert "samples/s" not in out  # the last: no step this call


def test_a_resume_whose_start_up_outlasted_its_budget_says_what_was_left_and_records_what_it_took(
        tiny_dataset, tmp_path):
    """The margin missed (a clock 30 s a reading: the first batch came long after the budget): no step, nothing
    to do with left_s and need_s; the leg's checkpoint records its own start-up in min_leg_s, so the next resume
    says nothing to do before it starts anything."""
    run = tmp_path / "run"
    train(small(2, time_budget_s=40.0), tiny_dataset, str(run), progress=False)
    time0 = json.loads((run / "state.json").read_text())["time_s"]
    end = train(small(4, time_budget_s=40.0), tiny_dataset, str(run), resume=True, progress=False,
                clock=SlowClock())
    assert (end["stopped_by"], end["why"], end["steps_run"]) == ("nothing_to_do", "budget_spent", 0)
    state = json.loads((run / "state.json").read_text())
    assert end["left_s"] == pytest.approx(40.0 - time0, abs=2e-3)
    assert state["min_leg_s"] >= 30.0 and end["need_s"] == pytest.approx(2 * state["min_leg_s"], abs=2e-3)


def test_resume_refuses_another_model_and_other_data_spelling_out_the_difference(tiny_dataset, tmp_path):
    from envisat_pose.pipelines.detector.train import train_detector

    run = str(tmp_path / "run")
    train_detector(small(2), [tiny_dataset], run, workers=0, progress=False)
    wider = TrainConfig(**{**small(4).__dict__, "model": ModelConfig(input_px=128, width=24, depth=2, stem_width=8)})
    with pytest.raises(InputError, match=r"model\.width 16 -> 24"):
        train_detector(wider, [tiny_dataset], run, resume=True, progress=False)
    other = tmp_path / "other"
    assert main(["generate", "--num-images", "2", "--shard-size", "2", "--resolution", "128", "--seed", "12",
                 "--out", str(other), "--quiet"]) == 0
    with pytest.raises(InputError, match=r"trained on ds \(8 images.*not on other \(2 images"):
        train_detector(small(4), [str(other)], run, resume=True, progress=False)
    end = train_detector(small(4), [tiny_dataset], run, resume=True, progress=False, command="envisat again")
    assert end["step"] == 4 and end["steps_run"] == 2  # the same data: goes on
    record = json.load(open(os.path.join(run, "config.json")))
    assert record["train"]["steps"] == 4 and record["resumes"][0]["command"] == "envisat again"
    assert record["resumes"][0]["step"] == 2


@pytest.mark.parametrize("under", [False, True])
def test_out_on_or_under_a_file_is_one_line(tiny_dataset, tmp_path, capsys, under):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    out = blocker / "run" if under else blocker
    err = one_line_error(capsys, main(["train", "--data", tiny_dataset, "--out", str(out), "--steps", "1",
                                       "--quiet"]))
    assert "--out" in err
    assert blocker.read_text() == "x"


@pytest.mark.parametrize("flag, value", [("--resolution", "256"), ("--uses-per-frame", "2"), ("--render-workers", "1"),
                                         ("--generate-config", "x.toml"), ("--looks", "y.toml")])
def test_online_flags_with_shards_are_refused(tiny_dataset, tmp_path, capsys, flag, value):
    """Flags of online training given to a run on shards were ignored without a word (the run trained as if
    they were not there): one line naming the flag, nothing written."""
    out = tmp_path / "run"
    err = one_line_error(capsys, main(["train", "--data", tiny_dataset, "--out", str(out), "--steps", "1", flag,
                                       value, "--quiet"]))
    assert err.startswith(f"envisat train: error: {flag}: a flag of --online training") and not out.exists(), err


def test_shards_for_another_target_name_the_flag_typed(tiny_dataset, tmp_path, capsys):
    out = tmp_path / "run"
    err = one_line_error(capsys, main(["train", "--target", "models/upper_stage.xml", "--data", tiny_dataset,
                                       "--out", str(out), "--steps", "1", "--quiet"]))
    assert "--data and --target: train on shards or on rendered frames" in err and not out.exists(), err


def test_the_record_holds_the_command_as_typed_and_reproduces_the_config(tiny_dataset, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    os.symlink(tiny_dataset, "data")
    (tmp_path / "small.toml").write_text(SMALL_TOML)
    argv = ["train", "--data", "data", "--out", "runs/det", "--config", "small.toml", "--steps", "2", "--seed",
            "3", "--workers", "0", "--quiet"]
    assert main(argv) == 0  # runs/ did not exist: parents are made
    record = json.load(open("runs/det/config.json"))
    assert record["command"] == "envisat train --data data --out runs/det --config small.toml --steps 2 --seed 3 " \
                                "--workers 0 --quiet"
    again = shlex.split(record["command"])[1:]
    again[again.index("runs/det")] = "runs/again"
    assert main(again) == 0
    assert json.load(open("runs/again/config.json"))["train"] == record["train"]


def test_a_budgets_bar_stops_at_its_end_when_the_last_step_ends_after_it(capsys):
    from envisat_pose.perception.trainer_hooks import advance_budget_bar, progress_bar

    bar = progress_bar(small(time_budget_s=4.0).steps, {"step": 0}, 4.0, 0.0, True)
    for seconds in (1.2, 3.9, 4.6, 5.3):  # the last two after the budget's end
        advance_budget_bar(bar, seconds)
        bar.refresh()
    bar.close()
    err = capsys.readouterr().err
    assert "4/4 s of the budget" in err and "100%" in err


def test_ctrl_c_writes_a_checkpoint_and_resume_honours_a_new_budget(tiny_dataset, tmp_path):
    """Ctrl-C reaches the whole process group (trainer and its worker) as from a terminal: the run stops after its
    step with a checkpoint and a resume hint (rc 130); `--resume --time-budget-s` trains that many seconds more."""
    (tmp_path / "small.toml").write_text(SMALL_TOML)
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "envisat_pose.app.cli", "train", "--data", tiny_dataset, "--out", str(run),
           "--config", str(tmp_path / "small.toml"), "--workers", "1", "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env=dict(os.environ, OMP_NUM_THREADS="1"))
    deadline = time.monotonic() + 120
    while not (run / "config.json").exists() and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.2)
    time.sleep(1.0)
    os.killpg(proc.pid, signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and err.count("go on with") == 1, err
    state = json.load(open(run / "state.json"))
    assert state["step"] >= 1 and (run / "checkpoint.safetensors").exists()
    # the hint as printed, run as a user would paste it, with a new budget
    hint = shlex.split(err.strip().split("go on with: ")[1])
    assert hint[:3] == ["envisat", "train", "--resume"]
    resumed = subprocess.run([sys.executable, "-m", "envisat_pose.app.cli", *hint[1:], "--time-budget-s", "20",
                              "--quiet"], capture_output=True, text=True, timeout=180)
    assert resumed.returncode == 0, resumed.stderr
    after = json.load(open(run / "state.json"))
    assert after["step"] > state["step"] + 1, resumed.stdout  # the loaders' start-up spends no budget of the steps
    assert after["time_s"] - state["time_s"] <= 20.0
    assert "(time_budget)" in resumed.stdout
    # after a budgeted leg, --steps alone trains to that step
    more = subprocess.run([sys.executable, "-m", "envisat_pose.app.cli", *hint[1:], "--steps",
                           str(after["step"] + 2), "--quiet"], capture_output=True, text=True, timeout=180)
    assert more.returncode == 0, more.stderr
    assert json.load(open(run / "state.json"))["step"] == after["step"] + 2


def test_a_plain_script_without_a_main_guard_trains_with_workers(tiny_dataset, tmp_path):
    script = tmp_path / "plain.py"
    script.write_text(textwrap.dedent(f"""
        from envisat_pose.perception.data import DataConfig
        from envisat_pose.perception.model import ModelConfig
        from envisat_pose.perception.train import TrainConfig
        from envisat_pose.pipelines.detector.train import train_detector

        cfg = TrainConfig(steps=2, batch_size=2, warmup_steps=1,
                          model=ModelConfig(input_px=128, width=16, depth=2, stem_width=8),
                          data=DataConfig(input_px=128))
        end = train_detector(cfg, {tiny_dataset!r}, {str(tmp_path / "run")!r}, workers=1, progress=False)
        print("TRAINED", end["step"])
    """))
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=180, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.count("TRAINED") == 1 and "TRAINED 2" in done.stdout


def test_negative_loss_weights_are_refused():
    from envisat_pose.perception.losses import LossConfig

    with pytest.raises(ConfigError, match="heatmap = -1"):
        LossConfig(heatmap=-1.0)  # it trained, to loss -3.5
    with pytest.raises(ConfigError, match="loss.line"):
        from_dict(TrainConfig, {"loss": {"line": -0.5}})


def test_a_diverged_run_stops_and_keeps_its_last_good_checkpoint(tiny_dataset, tmp_path, monkeypatch):
    """Weights gone non-finite at the optimizer's fourth step (a fault put in the optimizer: the learning rates
    that once made it happen, such as 1e9, are refused by the config now) stop the run with one line naming the
    step and the rate (it ended "loss nan" with exit 0 and wrote the NaN weights over the checkpoint); what the
    folder holds is a consistent, finite checkpoint of an earlier step."""
    import torch

    from envisat_pose.perception import train as train_module
    from envisat_pose.perception.trainer_hooks import TrainingDiverged
    from envisat_pose.perception.weights import read_weights

    made = train_module.make_optimizer

    def failing_optimizer(model, cfg, dev):
        opt = made(model, cfg, dev)
        step, calls = opt.step, []

        def step_then_fail(*args, **kwargs):
            out = step(*args, **kwargs)
            calls.append(1)
            if len(calls) == 4:
                with torch.no_grad():
                    next(model.parameters()).fill_(float("nan"))
            return out

        opt.step = step_then_fail
        return opt

    monkeypatch.setattr(train_module, "make_optimizer", failing_optimizer)
    run = str(tmp_path / "run")
    cfg = from_dict(TrainConfig, {**small(40).to_dict(), "checkpoint_every": 1})
    with pytest.raises(TrainingDiverged, match=r"training diverged by step \d+: .* not finite \(learning rate "):
        train(cfg, tiny_dataset, run, workers=0, progress=False)
    state = json.load(open(os.path.join(run, "state.json")))
    weights, meta = read_weights(os.path.join(run, "checkpoint.safetensors"))
    assert meta["step"] == str(state["step"]) and 1 <= state["step"] < 40
    assert all(torch.isfinite(t).all() for t in weights.values() if t.is_floating_point())


def test_a_resume_refuses_checkpoint_files_of_two_steps(tiny_dataset, tmp_path, capsys):
    """A kill while the checkpoint was written leaves checkpoint.safetensors of step n + 1 beside state.json of
    step n (written last): the resume says so in one line (it went on, mixing them: every weight differed from the
    uninterrupted run's); a state.json that is not JSON is one line too."""
    from safetensors.torch import save_file

    from envisat_pose.perception.weights import read_weights

    (tmp_path / "small.toml").write_text(SMALL_TOML.replace("steps = 100000", "steps = 2"))
    run = tmp_path / "run"
    assert main(["train", "--data", tiny_dataset, "--out", str(run), "--config", str(tmp_path / "small.toml"),
                 "--workers", "0", "--quiet"]) == 0
    weights, meta = read_weights(str(run / "checkpoint.safetensors"))
    resume = ["train", "--resume", "--data", tiny_dataset, "--out", str(run), "--steps", "4", "--quiet"]
    save_file(weights, str(run / "checkpoint.safetensors"), metadata={**meta, "step": "3"})  # the next step's
    err = one_line_error(capsys, main(resume))
    assert "checkpoint.safetensors holds step 3, its state.json step 2" in err and "init" in err
    (run / "state.json").write_text("{half")
    assert "state.json cannot be read" in one_line_error(capsys, main(resume))


def test_a_run_resumes_with_the_ddp_world_it_ran_with(tiny_dataset, tmp_path, monkeypatch):
    """state.json records the DDP world; a resume under another count is refused, naming how to resume (a 2-rank
    run went on as one process, its data split and batches changed); a DDP run's resume hint is a torchrun
    command with its count."""
    import argparse

    from envisat_pose.app.train import resume_command
    from envisat_pose.perception.train_run import start_state

    run = str(tmp_path / "run")
    train(small(1), tiny_dataset, run, workers=0, progress=False)
    assert json.load(open(os.path.join(run, "state.json")))["world"] == 1
    with pytest.raises(InputError, match=r"trained by 1 DDP process\(es\), this is 2 .* in one process"):
        start_state(run, small(2), True, None, None, world=2)
    args = argparse.Namespace(data=[tiny_dataset], out=run)
    assert resume_command(args).startswith("envisat train --resume --data")
    monkeypatch.setenv("WORLD_SIZE", "")  # empty: unset, as pools.torchrun_int reads it (was `--nproc-per-node ''`)
    assert resume_command(args).startswith("envisat train --resume --data")
    monkeypatch.setenv("WORLD_SIZE", "  ")  # blank: unset too
    assert resume_command(args).startswith("envisat train --resume --data")
    monkeypatch.setenv("WORLD_SIZE", "2")
    assert resume_command(args).startswith("torchrun --nproc-per-node 2 --master-addr 127.0.0.1 -m "
                                           "envisat_pose.app.cli train --resume --data")


def test_an_out_that_cannot_be_made_is_refused_before_training(tmp_path, capsys):
    """`--out /proc/run` was a FileNotFoundError traceback after the first step (the run folder is made then):
    now one line before any work; a makeable --out leaves nothing behind the check."""
    from envisat_pose.out_dirs import check_makeable

    err = one_line_error(capsys, main(["train", "--online", "--out", "/proc/envisat_run", "--steps", "2", "--quiet"]))
    assert "--out '/proc/envisat_run': cannot be made or written" in err
    check_makeable(str(tmp_path / "a" / "b"))
    assert os.listdir(tmp_path) == []


def test_a_new_run_into_a_folder_of_other_files_is_refused(tiny_dataset, tmp_path, capsys):
    """A copy of a dataset given as --out took the run's files beside its shards and manifest: refused in one line
    naming them; a run folder's own files (a run killed before its first checkpoint) and hidden files are not in
    the way."""
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(tiny_dataset, copy)
    err = one_line_error(capsys, main(["train", "--data", tiny_dataset, "--out", str(copy), "--steps", "1",
                                       "--quiet"]))
    assert "holds files that are not a training run's (generate.config.toml, manifest.json" in err
    assert not (copy / "config.json").exists()
    own = tmp_path / "own"
    own.mkdir()
    (own / "config.json").write_text("{}")
    (own / ".notes").write_text("mine")
    (tmp_path / "small.toml").write_text(SMALL_TOML.replace("steps = 100000", "steps = 1"))
    assert main(["train", "--data", tiny_dataset, "--out", str(own), "--config", str(tmp_path / "small.toml"),
                 "--workers", "0", "--quiet"]) == 0
    assert f"weights {own / 'checkpoint.safetensors'}" in capsys.readouterr().out  # the end line names the file


def test_a_run_stopped_before_its_first_checkpoint_is_said_to_be_so(tmp_path):
    from envisat_pose.perception.train_run import check_resume

    (tmp_path / "config.json").write_text("{}")
    with pytest.raises(InputError, match=r"no state.json\) \(it stopped before its first checkpoint: start it again"):
        check_resume(str(tmp_path), small(), None)  # it said "no config.json and state.json"
    with pytest.raises(InputError, match=r"no config.json and no state.json\)$"):
        check_resume(str(tmp_path / "empty"), small(), None)
