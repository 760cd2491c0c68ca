"""scripts/loop_sequences.py: the held-out sequences of the error model are the closed loop's own frames (the image
table `bench/tracking.py` resolves for the same scenario, seed and duration, its lit sun included), cut to the
frames asked for."""

import dataclasses
import importlib.util
import os

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def load(path):
    spec = importlib.util.spec_from_file_location(os.path.basename(path)[:-3], path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_held_out_sequence_is_the_closed_loops_image_config():
    seqs = load(os.path.join(ROOT, "scripts", "loop_sequences.py"))
    bench = load(os.path.join(ROOT, "bench", "tracking.py"))
    for scenario in ("default", "slow-tumble"):
        cfg = seqs.sequence_config(scenario, 9001, 40)
        run = bench.run_config(scenario, 9001, os.path.join(ROOT, "models", "detector.safetensors"), 39.0, None,
                               90.0).image
        assert (cfg.mode, cfg.sequence.scenario, cfg.seed, cfg.num_images, cfg.shard_size) == ("sequence", scenario, 9001, 40, 40)
        assert cfg.sun_dir is not None and np.isclose(np.linalg.norm(cfg.sun_dir), 1.0, atol=1e-6)
        assert dataclasses.asdict(cfg) == dataclasses.asdict(dataclasses.replace(run, shard_size=40))
    other = seqs.sequence_config("default", 9002, 40)
    assert other.sun_dir != seqs.sequence_config("default", 9001, 40).sun_dir  # each seed its own sun


def test_an_abbreviated_flag_is_refused_not_read_as_another(tmp_path, capsys):
    """`--frame 2` was read as `--frames 2` (argparse's abbreviations; so was `--seed` as `--seeds`): it is a usage
    error now, before any frame is rendered."""
    seqs = load(os.path.join(ROOT, "scripts", "loop_sequences.py"))
    with pytest.raises(SystemExit) as stop:
        seqs.main(["--scenarios", "default", "--seeds", "9001", "--frame", "2", "--out", str(tmp_path / "held_out")])
    assert stop.value.code == 2 and "unrecognized arguments: --frame 2" in capsys.readouterr().err
    assert not (tmp_path / "held_out").exists()
