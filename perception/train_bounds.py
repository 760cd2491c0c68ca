"""The bounds of a training config (perception/train.TrainConfig and keypoint_train.KeypointTrainConfig), each
with the reason a value beyond it gives no meaningful run (a traceback, NaN weights, a run that never moves a
weight, a batch no memory holds); TrainConfig.validate calls check_train_config. The model's own bounds live in
model.py (check_backbone), the crops' in data.py (DataConfig.validate), the losses' in losses.py."""

from __future__ import annotations

import torch

from envisat_pose.config import check

# lr: AdamW moves each weight by about lr per step whatever the gradient's scale. Below float32's least normal
# number (1.2e-38) the rate is 0 in the weights' arithmetic: no weight moves (1e-300 "trained" to the loss it
# started at). Above 1 every weight (He-initialised, ~0.07 at 48 channels) moves many times its size each step;
# at 1e300 the optimizer failed to convert the rate to float (a RuntimeError at the first step).
MIN_LR = float(torch.finfo(torch.float32).tiny)
MAX_LR = 1.0
# AdamW scales each weight by 1 - lr x weight_decay per step: beyond 1 the factor is negative and the weights flip
# sign and grow every step (1e300: every weight NaN by step 2, the error blaming the learning rate)
MAX_DECAY_FACTOR = 1.0
# batch_size: the stem's first feature map alone holds batch x stem_width x (input_px / 2)^2 float32 values; over
# 2^31 of them (8 GiB, past torch's 32-bit index arithmetic of GPU kernels; the hourglass holds tens of such maps)
# no machine trains the batch (2^63 - 1 samples: a MemoryError building the DataLoader's first batch)
MAX_STEM_VALUES = 2**31
# seed: numpy's generators take no negative seed (a ValueError at the first sample); the seeds of every other job
# are below 2^63 (TOML's integers)
MAX_SEED = 2**63 - 1


def check_train_config(cfg, p: str) -> None:
    """ConfigError naming the first of cfg's fields (a TrainConfig's) outside its range; p: the field prefix."""
    check(cfg.steps >= 1, f"{p}steps", cfg.steps, "at least 1 step")
    check_batch_and_lr(cfg.batch_size, cfg.lr, cfg.model, p)
    check(cfg.warmup_steps >= 1, f"{p}warmup_steps", cfg.warmup_steps, "at least 1 step")
    check(0 <= cfg.seed <= MAX_SEED, f"{p}seed", cfg.seed, "a non-negative integer seed below 2^63")
    check(cfg.time_budget_s is None or cfg.time_budget_s > 0, f"{p}time_budget_s", cfg.time_budget_s,
          "seconds > 0 (leave it out to train by steps)")
    check(cfg.schedule in ("cosine", "constant_cooldown"), f"{p}schedule", cfg.schedule,
          "'cosine' or 'constant_cooldown'")
    check(0 < cfg.cooldown_frac <= 1, f"{p}cooldown_frac", cfg.cooldown_frac, "a share of the run in (0, 1]")
    check(0 <= cfg.ema_decay < 1, f"{p}ema_decay", cfg.ema_decay, "a decay in [0, 1) (0: no average)")
    most_decay = MAX_DECAY_FACTOR / cfg.lr
    check(0 <= cfg.weight_decay <= most_decay, f"{p}weight_decay", cfg.weight_decay, f"a decay in [0, "
          f"{most_decay:g}] (1 / lr: AdamW scales each weight by 1 - lr x weight_decay per step)")
    check(cfg.checkpoint_every >= 1, f"{p}checkpoint_every", cfg.checkpoint_every, "at least 1 step")
    # the segments' ends jittered by more than the input's side lie off it: the verifier learns nothing (1e6 px:
    # its loss stayed at ln 2), and at 1e300 every weight was NaN by step 2
    check(0 <= cfg.line_jitter_px <= cfg.model.input_px, f"{p}line_jitter_px", cfg.line_jitter_px,
          f"pixels in [0, the model's input_px = {cfg.model.input_px}]")


def check_batch_and_lr(batch_size: int, lr: float, model, p: str) -> None:
    """ConfigError naming batch_size or lr (under prefix p) outside the bounds a run of `model` (a ModelConfig)
    takes: a training run's (check_train_config) and adapt's fine-tune's, checked when its job is built."""
    stem = model.stem_width * (model.input_px // 2) ** 2
    most = max(1, MAX_STEM_VALUES // max(1, stem))
    check(1 <= batch_size <= most, f"{p}batch_size", batch_size, f"1 to {most} samples per batch (batch x "
          f"stem_width x (input_px / 2)^2 at most 2^31 float32 values in the stem's first feature map)")
    check(MIN_LR <= lr <= MAX_LR, f"{p}lr", lr, f"a learning rate in [{MIN_LR:.3g}, {MAX_LR:g}] (below: "
          "0 in float32, no weight moves; AdamW moves each weight ~lr per step)")
