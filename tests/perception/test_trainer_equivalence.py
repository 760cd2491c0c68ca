"""The Trainer trains what its recipe says: the metrics lines, the learning rates and the final weights of a
seeded run equal a reference written out here step by step from the model, the losses and AdamW directly (no
Trainer, no hook): the warm-up and the cosine schedule as formulas, the line jitter's generator, the clipped
gradients, the epoch boundary's averages, and the moving average as its formula."""

import json
import math
import os

import torch

from envisat_pose.perception.data import DataConfig, shard_paths
from envisat_pose.perception.losses import corner_losses
from envisat_pose.perception.model import ModelConfig
from envisat_pose.perception.stream import epoch_batches
from envisat_pose.perception.train import TrainConfig, init_model, train
from envisat_pose.perception.weights import read_weights

STEPS, WARMUP, BATCH = 6, 2, 2  # 8 images: 4 batches an epoch, so an epoch line at step 4 and the end at 6


def config(**kw) -> TrainConfig:
    return TrainConfig(steps=STEPS, batch_size=BATCH, lr=2e-3, warmup_steps=WARMUP, seed=3, checkpoint_every=10 ** 6,
                       line_jitter_px=1.0, model=ModelConfig(input_px=128, width=16, depth=2, stem_width=8),
                       data=DataConfig(input_px=128), **kw)


def reference_lr(cfg: TrainConfig, step: int) -> float:
    """A linear warm-up over warmup_steps, then a cosine from the peak to 5 % over the remaining steps."""
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    frac = (step - cfg.warmup_steps) / (cfg.steps - cfg.warmup_steps)
    return cfg.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * frac)))


def reference_run(cfg: TrainConfig, data_dir: str):
    """Each step's loss terms, each step's rate and the weights after each step (float tensors, copies), trained
    without the Trainer."""
    model = init_model(cfg)
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay, foreach=True)
    paths = shard_paths(data_dir)
    terms, lrs, weights, step, epoch = [], [], [], 0, 0
    while step < cfg.steps:
        for batch in epoch_batches(paths, cfg.data, cfg.seed, epoch, cfg.batch_size, 0):
            if step == cfg.steps:
                break
            lrs.append(reference_lr(cfg, step))
            for group in opt.param_groups:
                group["lr"] = lrs[-1]
            out = model(batch["image"])
            noise = torch.randn(batch["segments_px"].shape,
                                generator=torch.Generator().manual_seed(cfg.seed * 1_000_003 + step))
            logits = model.line_logits(out["features"], batch["segments_px"] + cfg.line_jitter_px * noise)
            t = corner_losses(out, batch, logits, cfg.loss, cfg.model.stride)
            opt.zero_grad(set_to_none=True)
            t["loss"].backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0, foreach=True)
            opt.step()
            terms.append({k: v.detach() for k, v in t.items()})
            weights.append({k: v.detach().clone() for k, v in model.state_dict().items() if v.is_floating_point()})
            step += 1
        epoch += 1
    return terms, lrs, weights


def mean_terms(terms: list[dict]) -> dict:
    """The terms averaged as a metrics line holds them: summed as float32 tensors, then divided."""
    sums = {}
    for t in terms:
        sums = {k: sums[k] + v if k in sums else v for k, v in t.items()}
    return {k: float(v) / len(terms) for k, v in sums.items()}


def test_a_seeded_run_equals_its_step_by_step_reference(tiny_dataset, tmp_path):
    torch.set_num_threads(1)
    d = 0.75
    cfg = config(ema_decay=d)
    run = str(tmp_path / "run")
    end = train(cfg, tiny_dataset, run, progress=False, workers=0)
    lines = [json.loads(x) for x in open(os.path.join(run, "metrics.jsonl"))]
    terms, lrs, after_step = reference_run(cfg, tiny_dataset)
    assert [(x["kind"], x["epoch"], x["step"]) for x in lines] == [("epoch", 0, 4), ("end", 1, 6)]
    for line, (a, b) in zip(lines, [(0, 4), (4, 6)]):
        expect = mean_terms(terms[a:b])
        assert len(expect) >= 5 and {k: line[k] for k in expect} == expect, line["kind"]  # bit for bit
        assert line["lr"] == lrs[b - 1]
    assert end == lines[-1] and end["steps_run"] == STEPS and end["stopped_by"] == "steps"
    weights, _ = read_weights(os.path.join(run, "checkpoint.safetensors"))
    last = after_step[-1]
    assert len(last) > 20 and all(torch.equal(weights[k], last[k]) for k in last)
    # the moving average as its formula: a_1 = w_1, a_n = d a_(n-1) + (1 - d) w_n
    averaged = dict(after_step[0])
    for w in after_step[1:]:
        averaged = {k: d * averaged[k] + (1 - d) * w[k] for k in averaged}
    ema, _ = read_weights(os.path.join(run, "ema.safetensors"))
    for k in averaged:
        assert torch.allclose(ema[k], averaged[k], rtol=1e-5, atol=1e-7), k
    assert any(not torch.allclose(ema[k], last[k]) for k in averaged)
