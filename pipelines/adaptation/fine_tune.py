"""Step 4 of `envisat adapt` (pipelines/adaptation/adapt.py): fine-tune the detector on the pseudo-labelled frames
in memory, through the project's Trainer (perception/train.py: its schedule, its step, its crops, augmentation
and losses) with a hook of its own, and write the adapted weights with the base weights' metadata."""

from __future__ import annotations

import json

import numpy as np
import torch
from torch.utils.data import default_collate

from envisat_pose.config import from_dict
from envisat_pose.perception.data import DataConfig, decode_label, make_sample
from envisat_pose.perception.model import ModelConfig
from envisat_pose.perception.train import TrainConfig, Trainer
from envisat_pose.perception.train_bounds import check_batch_and_lr
from envisat_pose.perception.trainer_hooks import Hook
from envisat_pose.perception.weights import load_model, read_header, read_metadata, save_weights
from envisat_pose.perception.weights_keys import FORMAT_KEY, MODEL_CONFIG_KEY

ADAPT_PARAMS = ("norm_heads", "all", "none")  # what the fine-tune trains (AdaptConfig.params)


def trainable(model, params: str) -> list:
    """The parameters fine-tuned: every one ('all'), the normalization layers' and the heads' ('norm_heads':
    batch-norm affine weights, the junction head, the line head), or none ('none')."""
    if params == "all":
        return list(model.parameters())
    if params == "none":
        return []
    chosen = {id(p) for m in model.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)
              for p in m.parameters()}
    for name in ("jhead", "line_reduce", "line_mlp"):
        chosen |= {id(p) for p in getattr(model, name).parameters()}
    return [p for p in model.parameters() if id(p) in chosen]


def check_fine_tune(cfg, p: str) -> None:
    """ConfigError naming cfg's batch_size or lr (cfg: an AdaptConfig; p its prefix) outside what the fine-tune's
    TrainConfig takes for the network in cfg.track.weights (its architecture read from the file's header), when
    the job is built: the fine-tune builds that TrainConfig after the first round's track (minutes of work; a batch
    of 1e12 was refused there)."""
    model = from_dict(ModelConfig, json.loads(read_header(cfg.track.weights)[MODEL_CONFIG_KEY]))
    check_batch_and_lr(cfg.batch_size, cfg.lr, model, p)


class FineTuneLosses(Hook):
    """The fine-tune's loss after every step, read back (its figures and the bar's postfix)."""

    def __init__(self, bar=None):
        self.bar = bar
        self.losses: list[float] = []

    def after_step(self, terms: dict) -> None:
        self.losses.append(float(terms["loss"]))
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix_str(f"loss {self.losses[-1]:.3f}", refresh=False)


def label_batches(images: list[np.ndarray], labels: list[dict], data, batch_size: int, steps: int,
                  rng: np.random.Generator):
    """`steps` batches for the Trainer, (batch, {}): batch_size frames drawn with replacement, each cropped and
    augmented as in training (perception/data.make_sample with DataConfig data) around its label."""
    decoded = [decode_label(json.dumps(lab).encode(), f"pseudo-label {i}") for i, lab in enumerate(labels)]
    for _ in range(steps):
        pick = rng.integers(0, len(images), size=batch_size)
        yield default_collate([make_sample(images[i], decoded[i], data, rng) for i in pick]), {}


def fine_tune(weights: str, images: list[np.ndarray], labels: list[dict], cfg, seed: np.random.SeedSequence,
              bar=None) -> tuple[object, dict]:
    """Fine-tune the detector in `weights` on (image, label) pairs (label: pseudo_labels.label_record's fields)
    for cfg.steps AdamW steps of cfg.batch_size at peak rate cfg.lr (cfg: the AdaptConfig; the trainer's warm-up
    and cosine schedule, a warm-up of a tenth of the steps, at most 20), only the parameters cfg.params names,
    the batch norms' running statistics frozen (a batch of one sequence's frames is no population), on
    cfg.device. Returns the model (CPU, eval mode) and {loss_first, loss_last (mean of the first and last tenth
    of the steps), steps, trainable (parameters)}."""
    model = load_model(weights, device=cfg.device)
    params = trainable(model, cfg.params)
    if not params:
        return model.cpu().eval(), {"steps": 0, "trainable": 0, "loss_first": None, "loss_last": None}
    for p in model.parameters():
        p.requires_grad_(False)
    for p in params:
        p.requires_grad_(True)
    model.train()
    for m in model.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.eval()
    data = DataConfig(input_px=model.cfg.input_px, stride=model.cfg.stride)
    tcfg = TrainConfig(steps=cfg.steps, batch_size=cfg.batch_size, lr=cfg.lr,
                       warmup_steps=max(1, min(20, cfg.steps // 10)), seed=int(seed.generate_state(1)[0]),
                       model=model.cfg, data=data)
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=0.0)
    losses = FineTuneLosses(bar)
    batches = label_batches(images, labels, data, cfg.batch_size, cfg.steps, np.random.default_rng(seed))
    Trainer(tcfg, model, opt, dev=torch.device(cfg.device), hooks=[losses]).run(batches)
    tenth = max(1, len(losses.losses) // 10)
    return model.cpu().eval(), {"steps": cfg.steps, "trainable": int(sum(p.numel() for p in params)),
                                "loss_first": float(np.mean(losses.losses[:tenth])),
                                "loss_last": float(np.mean(losses.losses[-tenth:]))}


def save_adapted(model, base: str, path: str, extra: dict, drop: tuple[str, ...] = ()) -> bool:
    """Write the model's tensors with the base weights' metadata (error model, face cue, ...) less the keys in
    drop (perception/weights_keys.py's *_KEYS: what the base's fits measured on the network before the fine-tune)
    and `extra` on top. False (nothing written) when a tensor is not finite (a diverged fine-tune)."""
    if not all(torch.isfinite(v).all() for v in model.state_dict().values() if v.is_floating_point()):
        return False
    meta = {k: v for k, v in read_metadata(base).items() if k not in (FORMAT_KEY, MODEL_CONFIG_KEY, *drop)}
    save_weights(path, model, {**meta, **extra})
    return True
