"""Training: an honest overfit check on a tiny generated set, exact resume, the run directory, CLI errors."""

import json
import os

import pytest
import torch

from envisat_pose.app.cli import main
from envisat_pose.perception.data import DataConfig
from envisat_pose.perception.model import ModelConfig
from envisat_pose.perception.train import TrainConfig, train
from envisat_pose.perception.weights import load_model


def small_config(steps, **kw):
    return TrainConfig(steps=steps, batch_size=4, lr=3e-3, warmup_steps=20, checkpoint_every=10**6,
                       model=ModelConfig(input_px=128, width=24, depth=2, stem_width=16),
                       data=DataConfig(input_px=128, **kw))


def metrics(run):
    return [json.loads(line) for line in open(os.path.join(run, "metrics.jsonl"))]


def test_overfit_drives_the_loss_down(tiny_dataset, tmp_path):
    """200 steps on 8 images without augmentation: every term falls far below where it started."""
    torch.set_num_threads(1)
    run = str(tmp_path / "run")
    train(small_config(200, augment=False, crop_scale_jitter=0.0, crop_shift_jitter=0.0, whole_frame_prob=0.0),
          tiny_dataset, run, progress=False)
    m = metrics(run)
    first, last = m[0], m[-1]
    print([(d["step"], round(d["heatmap"], 3), round(d["offset"], 3), round(d["line"], 3)) for d in m[::10]])
    assert last["step"] == 200
    assert last["heatmap"] < 0.15 * first["heatmap"]
    assert last["offset"] < 0.3 * first["offset"]
    assert last["line"] < 0.3 * first["line"]
    assert last["nll"] < first["nll"] - 2.0
    model = load_model(os.path.join(run, "checkpoint.safetensors"))
    assert model.cfg.input_px == 128
    cfg = json.load(open(os.path.join(run, "config.json")))
    assert cfg["train"]["steps"] == 200


def test_resume_equals_an_uninterrupted_run(tiny_dataset, tmp_path):
    torch.set_num_threads(1)
    whole, part = str(tmp_path / "whole"), str(tmp_path / "part")
    train(small_config(6), tiny_dataset, whole, progress=False)
    train(small_config(3), tiny_dataset, part, progress=False)  # stops mid-epoch (2 batches per epoch)
    train(small_config(6), tiny_dataset, part, resume=True, progress=False)
    a = load_model(os.path.join(whole, "checkpoint.safetensors")).state_dict()
    b = load_model(os.path.join(part, "checkpoint.safetensors")).state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert json.load(open(os.path.join(part, "state.json")))["step"] == 6


def test_resume_after_a_crash_past_the_warmup(tiny_dataset, tmp_path, monkeypatch):
    """A run killed in its cosine phase goes on from its last checkpoint (the optimizer state written there holds
    the schedule's learning rate and must read back with weights_only=True) and ends where an uninterrupted run
    ends."""
    import envisat_pose.perception.train as train_module

    torch.set_num_threads(1)
    cfg = TrainConfig(**{**small_config(6).__dict__, "warmup_steps": 2, "checkpoint_every": 2})
    whole, part = str(tmp_path / "whole"), str(tmp_path / "part")
    train(cfg, tiny_dataset, whole, progress=False)
    real_to_device, calls = train_module.to_device, []

    def crash_on_the_fifth_batch(batch, device):
        calls.append(1)
        if len(calls) == 5:
            raise KeyboardInterrupt
        return real_to_device(batch, device)

    monkeypatch.setattr(train_module, "to_device", crash_on_the_fifth_batch)
    with pytest.raises(KeyboardInterrupt):
        train(cfg, tiny_dataset, part, progress=False)
    assert json.load(open(os.path.join(part, "state.json")))["step"] == 4  # past the warmup
    monkeypatch.setattr(train_module, "to_device", real_to_device)
    train(cfg, tiny_dataset, part, resume=True, progress=False)
    a = load_model(os.path.join(whole, "checkpoint.safetensors")).state_dict()
    b = load_model(os.path.join(part, "checkpoint.safetensors")).state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_same_seed_same_weights_other_seed_others(tiny_dataset, tmp_path):
    torch.set_num_threads(1)
    runs = {}
    for name, seed in (("a", 0), ("b", 0), ("c", 1)):
        cfg = TrainConfig(**{**small_config(2).__dict__, "seed": seed})
        train(cfg, tiny_dataset, str(tmp_path / name), progress=False)
        runs[name] = load_model(str(tmp_path / name / "checkpoint.safetensors")).state_dict()
    assert all(torch.equal(runs["a"][k], runs["b"][k]) for k in runs["a"])
    assert not all(torch.equal(runs["a"][k], runs["c"][k]) for k in runs["a"])


def test_cli_errors_are_one_line(tmp_path, capsys, tiny_dataset):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["train", "--data", str(empty), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip()
    assert "empty dataset" in err and "\n" not in err
    assert main(["train", "--data", tiny_dataset, "--out", str(tmp_path / "nope"), "--resume"]) == 2
    assert f"--out '{tmp_path / 'nope'}' does not exist: nothing to resume" in capsys.readouterr().err


def test_cli_trains_and_refuses_to_overwrite(tiny_dataset, tmp_path, capsys):
    toml = tmp_path / "t.toml"
    toml.write_text("checkpoint_every = 1000\n[model]\ninput_px = 128\nwidth = 16\ndepth = 2\n"
                    "[data]\ninput_px = 128\n")
    run = str(tmp_path / "run")
    args = ["train", "--data", tiny_dataset, "--out", run, "--config", str(toml), "--steps", "2", "--batch-size",
            "4", "--threads", "1", "--quiet"]
    assert main(args) == 0
    assert os.path.exists(os.path.join(run, "checkpoint.safetensors"))
    cfg = json.load(open(os.path.join(run, "config.json")))
    assert cfg["git"] and "--steps 2" in cfg["command"]
    assert main(args) == 2
    assert "already holds a run" in capsys.readouterr().err
    assert main(args[:-1] + ["--quiet", "--resume"]) == 0
    assert main(["train", "--resume", "--out", run, "--steps", "3"]) == 2  # a run on shards: its --data again
    err = capsys.readouterr().err
    assert f"--out {run!r} trained on shards" in err and "give them again with --data (" in err
    assert "\n" not in err.strip()


@pytest.mark.parametrize("bad", ["steps = 0\n", "[model]\ninput_px = 100\n", "[data]\ninput_px = 256\n"])
def test_bad_config(tmp_path, tiny_dataset, bad, capsys):
    toml = tmp_path / "t.toml"
    toml.write_text(bad)
    assert main(["train", "--data", tiny_dataset, "--out", str(tmp_path / "r"), "--config", str(toml)]) == 2


def test_init_starts_from_given_weights_and_reads_several_folders(tiny_dataset, tmp_path):
    """--init: step 0 of a new run starts from the given weights (not the seeded draw); two --data folders are
    read together."""
    torch.set_num_threads(1)
    base = str(tmp_path / "base")
    train(small_config(2), tiny_dataset, base, progress=False)
    given = os.path.join(base, "checkpoint.safetensors")
    other = TrainConfig(**{**small_config(1, augment=False).__dict__, "seed": 7, "lr": 1e-12, "warmup_steps": 1})
    train(other, [tiny_dataset, tiny_dataset], str(tmp_path / "ft"), progress=False, init_weights=given)
    a = dict(load_model(given).named_parameters())  # parameters: BatchNorm's running statistics move
    b = dict(load_model(str(tmp_path / "ft" / "checkpoint.safetensors")).named_parameters())
    assert all(torch.allclose(a[k], b[k], atol=1e-6) for k in a)
    train(other, [tiny_dataset, tiny_dataset], str(tmp_path / "fresh"), progress=False)
    c = dict(load_model(str(tmp_path / "fresh" / "checkpoint.safetensors")).named_parameters())
    assert not all(torch.allclose(a[k], c[k], atol=1e-6) for k in a)
    assert json.load(open(tmp_path / "ft" / "state.json"))["step"] == 1


def test_cli_init_errors(tmp_path, capsys, tiny_dataset):
    code = main(["train", "--data", tiny_dataset, "--out", str(tmp_path / "r"), "--init", str(tmp_path / "no.st")])
    assert code == 2 and "--init" in capsys.readouterr().err


def test_a_resumed_run_takes_the_threads_it_trained_with(tiny_dataset, tmp_path):
    """The floats of a step depend on torch's CPU threads: train_detector records them in config.json and a resume
    that names none takes them again (here from a process set to another count), so it ends as the uninterrupted
    run did; the caller's count is given back."""
    from envisat_pose.pipelines.detector.train import train_detector

    whole, part = str(tmp_path / "whole"), str(tmp_path / "part")
    torch.set_num_threads(2)
    train_detector(small_config(6), [tiny_dataset], whole, workers=0, threads=1)
    train_detector(small_config(3), [tiny_dataset], part, workers=0, threads=1)
    assert json.load(open(os.path.join(part, "config.json")))["threads"] == 1
    train_detector(small_config(6), [tiny_dataset], part, workers=0, resume=True)  # no threads: the run's own
    assert torch.get_num_threads() == 2
    a = load_model(os.path.join(whole, "checkpoint.safetensors")).state_dict()
    b = load_model(os.path.join(part, "checkpoint.safetensors")).state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    # a leg resumed at other threads records them (config.json kept the first leg's): the next resume takes them
    train_detector(small_config(7), [tiny_dataset], part, workers=0, resume=True, threads=2)
    record = json.load(open(os.path.join(part, "config.json")))
    assert record["threads"] == 2 and [r["threads"] for r in record["resumes"]] == [1, 2]


@pytest.mark.parametrize("buffer, warned", [(9, True), (8, False), (None, False)])
def test_a_shuffle_buffer_beyond_the_data_is_said_once_naming_both_numbers(tiny_dataset, tmp_path, capsys,
                                                                            buffer, warned):
    """data.shuffle_buffer 9 over the tiny dataset's 8 samples: one warning line naming both; 8 (all of them), or
    the default 64 nobody gave: none. The run trains either way, its config keeping the value given."""
    toml = tmp_path / "t.toml"
    given = "" if buffer is None else f"shuffle_buffer = {buffer}\n"
    toml.write_text(f"checkpoint_every = 1000\n[model]\ninput_px = 128\nwidth = 16\ndepth = 2\n"
                    f"[data]\ninput_px = 128\n{given}")
    run = tmp_path / "run"
    assert main(["train", "--data", tiny_dataset, "--out", str(run), "--config", str(toml), "--steps", "1",
                 "--batch-size", "4", "--threads", "1", "--workers", "0", "--quiet"]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "shuffle_buffer" in line]
    assert len(lines) == int(warned), lines
    if warned:
        assert "shuffle_buffer = 9" in lines[0] and "the 8 samples" in lines[0], lines
    assert json.loads((run / "config.json").read_text())["train"]["data"]["shuffle_buffer"] == (buffer or 64)
