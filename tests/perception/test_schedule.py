"""Legs that add up (issue 38): the constant rate with a cooldown, the weights kept at the cooldown's start, and
the moving average of the weights, against the formulas written out here."""

import json
import os

import numpy as np
import pytest
import torch

from envisat_pose.perception.data import DataConfig
from envisat_pose.perception.model import ModelConfig
from envisat_pose.perception.train import TrainConfig, lr_at, train
from envisat_pose.perception.weights import read_weights


def small(steps, **kw):
    return TrainConfig(steps=steps, batch_size=2, warmup_steps=2, checkpoint_every=10 ** 6, line_jitter_px=0.0,
                       model=ModelConfig(input_px=128, width=16, depth=2, stem_width=8),
                       data=DataConfig(input_px=128, augment=False), **kw)


def test_constant_then_a_sqrt_cooldown_to_zero():
    cfg = TrainConfig(steps=1002, warmup_steps=2, lr=1e-3, schedule="constant_cooldown", cooldown_frac=0.25)
    assert lr_at(cfg, 0) == pytest.approx(0.5e-3)  # warm-up
    assert lr_at(cfg, 2) == lr_at(cfg, 500) == lr_at(cfg, 752) == pytest.approx(1e-3)  # constant to 75 %
    for step in (800, 900, 1000):
        x = ((step - 2) / 1000 - 0.75) / 0.25
        assert lr_at(cfg, step) == pytest.approx(1e-3 * (1 - np.sqrt(x)))
    assert lr_at(cfg, 1002) == 0.0
    timed = TrainConfig(time_budget_s=100.0, warmup_steps=1, lr=1e-3, schedule="constant_cooldown",
                        cooldown_frac=0.5)
    assert lr_at(timed, 10, elapsed_s=40.0) == pytest.approx(1e-3)
    assert lr_at(timed, 10, elapsed_s=75.0) == pytest.approx(1e-3 * (1 - np.sqrt(0.5)))


def test_the_weights_at_the_cooldowns_start_are_kept_for_the_next_leg(tiny_dataset, tmp_path):
    torch.set_num_threads(1)
    run = str(tmp_path / "leg")
    train(small(6, schedule="constant_cooldown", cooldown_frac=0.5), tiny_dataset, run, progress=False)
    # steps 2..5 after the warm-up; the cooldown holds fractions above 0.5: from step 5 ((5 - 2) / 4 = 0.75)
    _, meta = read_weights(os.path.join(run, "pre_cooldown.safetensors"))
    assert meta["step"] == "5" and json.load(open(os.path.join(run, "state.json")))["pre_cooldown_step"] == 5
    pre, _ = read_weights(os.path.join(run, "pre_cooldown.safetensors"))
    end, _ = read_weights(os.path.join(run, "checkpoint.safetensors"))
    assert any(not torch.equal(pre[k], end[k]) for k in pre)  # the cooldown step moved them
    leg2 = str(tmp_path / "leg2")
    train(small(2), tiny_dataset, leg2, progress=False, init_weights=os.path.join(run, "pre_cooldown.safetensors"))
    assert os.path.exists(os.path.join(leg2, "checkpoint.safetensors"))


def test_a_budget_that_ends_before_the_cooldown_still_leaves_the_next_legs_start(tiny_dataset, tmp_path):
    """A budgeted run stops once its clock plus a reserve (at least 1 s) reaches the budget, so with the cooldown
    in the last 2 % of 8 s (after 7.84 s) no step can be in it: its last weights, never cooled, are the next
    leg's start (as on a slow machine, where the last steps come late)."""
    torch.set_num_threads(1)
    run = str(tmp_path / "leg")
    cfg = small(10 ** 6, time_budget_s=8.0, schedule="constant_cooldown", cooldown_frac=0.02)
    train(cfg, tiny_dataset, run, progress=False)
    state = json.load(open(os.path.join(run, "state.json")))
    pre, meta = read_weights(os.path.join(run, "pre_cooldown.safetensors"))
    end, _ = read_weights(os.path.join(run, "checkpoint.safetensors"))
    assert state["pre_cooldown_step"] == state["step"] == int(meta["step"]) > 0
    assert all(torch.equal(pre[k], end[k]) for k in pre)


def test_the_moving_average_follows_its_formula(tiny_dataset, tmp_path):
    """Warm-up rates do not depend on the run's length, so a 1-step run gives the weights after step 1: the
    average after step 2 is d W1 + (1 - d) W2 (the first update copies)."""
    torch.set_num_threads(1)
    d = 0.9
    one, two = str(tmp_path / "one"), str(tmp_path / "two")
    train(small(1, ema_decay=d), tiny_dataset, one, progress=False)
    train(small(2, ema_decay=d), tiny_dataset, two, progress=False)
    w1, _ = read_weights(os.path.join(one, "checkpoint.safetensors"))
    w2, _ = read_weights(os.path.join(two, "checkpoint.safetensors"))
    ema, meta = read_weights(os.path.join(two, "ema.safetensors"))
    assert meta["ema_decay"] == "0.9"
    names = [k for k in w1 if w1[k].is_floating_point() and "running" not in k]
    assert len(names) > 20
    for k in names:
        assert torch.allclose(ema[k], d * w1[k] + (1 - d) * w2[k], rtol=1e-5, atol=1e-7), k
    assert any(not torch.allclose(ema[k], w2[k]) for k in names)
