"""`envisat train --online` (issue 38): the trainer on frames rendered as training goes, end to end on the CPU: a
stopped run resumes where it stopped and ends with the weights of an uninterrupted one, no frame is cropped
more than K times, the record names the source; the verb refuses --data with --online."""

import json
import os

import pytest
import torch

from envisat_pose.app.cli import main
from envisat_pose.datagen.generate_config import GenerateConfig
from envisat_pose.perception.data import DataConfig
from envisat_pose.perception.model import ModelConfig
from envisat_pose.perception.train import TrainConfig
from envisat_pose.perception.weights import read_weights
from envisat_pose.pipelines.detector.train import OnlineConfig, train_detector

os.environ.setdefault("MUJOCO_GL", "osmesa")


def small(steps):
    return TrainConfig(steps=steps, batch_size=2, warmup_steps=1, checkpoint_every=10 ** 6,
                       model=ModelConfig(input_px=64, width=16, depth=2, stem_width=8),
                       data=DataConfig(input_px=64))


def online():
    return OnlineConfig(GenerateConfig(mode="random", resolution_px=128, seed=5, earth_probability=0.0),
                        workers=1, uses_per_frame=2)


def test_an_online_run_resumes_to_the_weights_of_an_uninterrupted_one(tmp_path):
    torch.set_num_threads(1)
    whole, part = str(tmp_path / "whole"), str(tmp_path / "part")
    end = train_detector(small(4), [], whole, online=online(), progress=False)
    assert end["step"] == 4 and end["uses_per_frame"] == 2 and end["max_uses"] == 2
    train_detector(small(2), [], part, online=online(), progress=False)
    state = json.load(open(os.path.join(part, "state.json")))
    assert state["online"]["step"] == 2 and state["online"]["next_frame"] == 2  # 2 frames a step, each used twice
    train_detector(small(4), [], part, resume=True, online=online(), progress=False)
    a, _ = read_weights(os.path.join(whole, "checkpoint.safetensors"))
    b, _ = read_weights(os.path.join(part, "checkpoint.safetensors"))
    assert all(torch.equal(a[k], b[k]) for k in a)
    record = json.load(open(os.path.join(whole, "config.json")))
    assert record["online"]["uses_per_frame"] == 2 and record["data"][0]["name"] == "online (default 100 %, K = 2)"
    configs = record["data"][0]["configs"]  # what a resume's refusal compares, the run's own numbers
    assert configs["generate"]["resolution_px"] == online().looks[0].generate.resolution_px and "data" in configs


def test_the_verb_takes_data_or_online_not_both(tmp_path, capsys):
    assert main(["train", "--data", str(tmp_path), "--online", "--out", str(tmp_path / "r"), "--quiet"]) == 2
    assert "not both" in capsys.readouterr().err
    assert main(["train", "--out", str(tmp_path / "r"), "--quiet"]) == 2
    assert "--online" in capsys.readouterr().err
    with pytest.raises(Exception, match="uses_per_frame"):
        OnlineConfig(GenerateConfig(mode="random"), uses_per_frame=9)
    assert main(["train", "--online", "--workers", "3", "--out", str(tmp_path / "r"), "--quiet"]) == 2
    assert "--workers: a flag of training on --data's shards" in capsys.readouterr().err  # it was ignored
    assert main(["train", "--online", "--render-workers", "0", "--out", str(tmp_path / "r"), "--quiet"]) == 2
    assert "--render-workers 0: expected at least 1" in capsys.readouterr().err  # it was the default count
    assert main(["train", "--resume", "--out", str(tmp_path / "none"), "--quiet"]) == 2
    assert "nothing to resume (no such folder)" in capsys.readouterr().err
    assert not os.path.exists(tmp_path / "r") and not os.path.exists(tmp_path / "none")


def test_a_resumed_online_run_refuses_shards_and_another_k(tmp_path, capsys):
    """--data on the resume of an online run was ignored (it went on online): refused, named as --resume; another
    --uses-per-frame is refused naming it."""
    torch.set_num_threads(1)
    run = str(tmp_path / "run")
    train_detector(small(1), [], run, online=online(), progress=False)
    assert main(["train", "--resume", "--data", str(tmp_path), "--out", run, "--steps", "3", "--quiet"]) == 2
    assert "--data and --resume: train on shards or on rendered frames, not both" in capsys.readouterr().err
    # another K on resume is named as K (it said resolution_px 128 -> 512: the looks rebuilt from defaults)
    assert main(["train", "--resume", "--uses-per-frame", "3", "--out", run, "--steps", "3", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "trained with uses_per_frame = 2, this call gives 3" in err and "resolution" not in err, err
    assert json.load(open(os.path.join(run, "state.json")))["step"] == 1


@pytest.mark.slow  # renders two looks at two sizes (~10 s)
def test_the_verb_trains_on_a_mix_of_looks_and_resumes_only_its_own(tmp_path, capsys):
    """`envisat train --online --looks`: a mix of a random look and a scenario's sequence at two sizes trains and
    records its looks; --resume goes on with them, and refuses a different looks file."""
    cfg = tmp_path / "train.toml"
    cfg.write_text("warmup_steps = 1\ncheckpoint_every = 1000000\n[model]\ninput_px = 64\nwidth = 16\ndepth = 2\n"
                   "stem_width = 8\n[data]\ninput_px = 64\n")
    looks = tmp_path / "looks.toml"
    looks.write_text('seed = 3\nearth_probability = 0.0\n[appearance]\ntexture_set_size = 1\n'
                     '[[look]]\nname = "random"\nweight = 2\nresolution_px = 128\n'
                     '[[look]]\nname = "slow"\nmode = "sequence"\nresolution_px = 96\nnum_images = 5\n'
                     '[look.sequence]\nscenario = "slow-tumble"\nframe_dt_s = 4.0\n')
    run = str(tmp_path / "run")
    common = ["--out", run, "--config", str(cfg), "--batch-size", "2", "--render-workers", "1", "--quiet"]
    assert main(["train", "--online", "--looks", str(looks), "--uses-per-frame", "2", "--steps", "2", *common]) == 0
    record = json.load(open(os.path.join(run, "config.json")))
    assert [(look["name"], look["share"]) for look in record["online"]["looks"]] == [("random", 67), ("slow", 33)]
    assert record["online"]["looks"][1]["generate"]["sequence"]["scenario"] == "slow-tumble"
    capsys.readouterr()
    assert main(["train", "--resume", "--steps", "3", *common]) == 0
    assert json.load(open(os.path.join(run, "state.json")))["step"] == 3
    other = tmp_path / "other.toml"
    other.write_text(looks.read_text().replace("weight = 2", "weight = 5"))
    assert main(["train", "--resume", "--steps", "4", "--looks", str(other), *common]) == 2
    err = capsys.readouterr().err
    assert "online (random 67 %, slow 33 %, K = 2)" in err and "random 83 %" in err and "Traceback" not in err
    assert json.load(open(os.path.join(run, "state.json")))["step"] == 3


ONLINE_TOML = """steps = 100000
batch_size = 2
warmup_steps = 1
checkpoint_every = 1
[model]
input_px = 64
width = 16
depth = 2
stem_width = 8
[data]
input_px = 64
"""


@pytest.mark.slow
def test_ctrl_c_to_the_process_group_stops_an_online_run_with_a_checkpoint(tmp_path):
    """A terminal's Ctrl-C reaches the trainer and its renderer processes: the renderers leave it to the trainer,
    which stops after its step with a checkpoint and the resume hint (rc 130; a renderer's KeyboardInterrupt was
    a traceback and no checkpoint)."""
    import signal
    import subprocess
    import sys
    import time

    (tmp_path / "small.toml").write_text(ONLINE_TOML)
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "envisat_pose.app.cli", "train", "--online", "--out", str(run), "--config",
           str(tmp_path / "small.toml"), "--resolution", "128", "--render-workers", "1", "--threads", "1"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env=dict(os.environ, OMP_NUM_THREADS="1"))
    deadline = time.monotonic() + 180
    while proc.poll() is None and time.monotonic() < deadline and not (run / "state.json").exists():
        time.sleep(0.2)  # a checkpoint every step: the run has trained once state.json is there
    os.killpg(proc.pid, signal.SIGINT)
    out, err = proc.communicate(timeout=180)
    assert proc.returncode == 130, err[-2000:]
    assert "Traceback" not in err and err.count("go on with") == 1, err[-2000:]
    state = json.load(open(run / "state.json"))
    assert state["step"] >= 1 and (run / "checkpoint.safetensors").exists()


@pytest.mark.slow
def test_a_plain_script_without_a_main_guard_trains_online(tmp_path):
    """The renderer processes are spawned without re-running the caller's script (it would start the job again in
    each and fail), as the shard workers are."""
    import subprocess
    import sys
    import textwrap

    script = tmp_path / "plain.py"
    script.write_text(textwrap.dedent(f"""
        from envisat_pose.datagen.generate_config import GenerateConfig
        from envisat_pose.perception.data import DataConfig
        from envisat_pose.perception.model import ModelConfig
        from envisat_pose.perception.train import TrainConfig
        from envisat_pose.pipelines.detector.train import OnlineConfig, train_detector

        cfg = TrainConfig(steps=2, batch_size=2, warmup_steps=1, model=ModelConfig(input_px=64, width=16, depth=2,
                          stem_width=8), data=DataConfig(input_px=64))
        online = OnlineConfig(GenerateConfig(mode="random", resolution_px=128, seed=5, earth_probability=0.0),
                              workers=1, uses_per_frame=2)
        end = train_detector(cfg, [], {str(tmp_path / "run")!r}, online=online, progress=False)
        print("TRAINED", end["step"])
    """))
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.count("TRAINED") == 1 and "TRAINED 2" in done.stdout
