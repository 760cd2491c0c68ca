"""The training step without boolean indexing gives the step of the plain form: the losses against an indexed
reference written here (CenterNet's focal loss, L1 offsets and the covariance NLL over the junction cells only),
and one optimizer step (multi-tensor AdamW and clipping) against the per-parameter loop, on a real batch."""

import copy

import numpy as np
import torch
import torch.nn.functional as F

from envisat_pose.perception.data import DataConfig, make_sample, read_samples, shard_paths
from envisat_pose.perception.losses import LossConfig, corner_losses
from envisat_pose.perception.model import ModelConfig
from envisat_pose.perception.stream import collate_batch
from envisat_pose.perception.train import TrainConfig, _train_step, init_model


def indexed_losses(out, batch, line_logits, cfg, stride):
    """The terms with boolean indexing (the form before the optimization), computed independently."""
    logit, target = out["jmap_logit"], batch["jmap"]
    p = torch.sigmoid(logit).clamp(1e-6, 1 - 1e-6)
    pos = target >= 1.0
    pos_loss = -((1 - p) ** cfg.focal_alpha * F.logsigmoid(logit))[pos].sum()
    neg_loss = -(((1 - target) ** cfg.focal_beta) * p ** cfg.focal_alpha * F.logsigmoid(-logit))[~pos].sum()
    focal = (pos_loss + neg_loss) / pos.sum().clamp(min=1)
    mask = batch["jmask"] > 0
    n = mask.sum().clamp(min=1)
    off_pred = out["joff"].permute(0, 2, 3, 1)[mask]
    off_true = batch["joff"].permute(0, 2, 3, 1)[mask]
    offset = (off_pred - off_true).abs().sum() / n
    e = (off_pred.detach() - off_true) * stride
    a, b, c = out["jchol"].permute(0, 2, 3, 1)[mask].unbind(-1)
    z1 = e[:, 0] / torch.exp(a)
    z2 = (e[:, 1] - c * z1) / torch.exp(b)
    nll = (0.5 * (z1 ** 2 + z2 ** 2) + a + b).sum() / n
    w = batch["line_weight"]
    line = (F.binary_cross_entropy_with_logits(line_logits, batch["line_label"], reduction="none") * w).sum() \
        / w.sum().clamp(min=1)
    total = cfg.heatmap * focal + cfg.offset * offset + cfg.nll * nll + cfg.line * line
    return {"loss": total, "heatmap": focal, "offset": offset, "nll": nll, "line": line}


def small_cfg():
    return TrainConfig(steps=10, batch_size=4, warmup_steps=1, line_jitter_px=0.0,
                       model=ModelConfig(input_px=128, width=24, depth=2, stem_width=16),
                       data=DataConfig(input_px=128))


def real_batch(tiny_dataset, cfg):
    samples = []
    for j, (_, image, label) in enumerate(read_samples(shard_paths(tiny_dataset))):
        samples.append(make_sample(image, label, cfg.data, np.random.default_rng([5, j])))
        if len(samples) == cfg.batch_size:
            break
    return collate_batch(samples)


def test_losses_without_indexing_equal_the_indexed_form(tiny_dataset):
    gen = torch.Generator().manual_seed(0)
    cfg = small_cfg()
    batch = real_batch(tiny_dataset, cfg)
    assert int((batch["jmask"] > 0).sum()) > 4  # junctions to weigh
    model = init_model(cfg)
    out = model(batch["image"])
    # heads that moved away from their calm start, with the covariance logits spread wide
    out = {k: v + 0.5 * torch.randn(v.shape, generator=gen) for k, v in out.items()}
    out["jchol"] = out["jchol"] * 3.0
    logits = model.line_logits(out["features"], batch["segments_px"])
    new = corner_losses(out, batch, logits, LossConfig(), 4)
    ref = indexed_losses(out, batch, logits, LossConfig(), 4)
    for k in ref:
        assert torch.allclose(new[k], ref[k], rtol=1e-5, atol=1e-6), (k, float(new[k]), float(ref[k]))
    # and the gradients they give the outputs
    params = [out["jmap_logit"], out["joff"], out["jchol"]]
    g_new = torch.autograd.grad(new["loss"], params, retain_graph=True)
    g_ref = torch.autograd.grad(ref["loss"], params)
    for a, b in zip(g_new, g_ref):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-7)


def test_an_extreme_covariance_logit_off_the_junctions_leaves_the_gradient_finite(tiny_dataset):
    cfg = small_cfg()
    batch = real_batch(tiny_dataset, cfg)
    model = init_model(cfg)
    out = dict(model(batch["image"]))
    off = (batch["jmask"] == 0)[:, None].expand_as(out["jchol"])
    out["jchol"] = torch.where(off, torch.full_like(out["jchol"], -200.0), out["jchol"])  # exp(200): overflow
    logits = model.line_logits(out["features"], batch["segments_px"])
    loss = corner_losses(out, batch, logits, LossConfig(), 4)["loss"]
    loss.backward()
    assert torch.isfinite(loss)
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_the_optimized_step_equals_the_plain_one(tiny_dataset):
    """Two steps with foreach AdamW and clipping give the weights of the per-parameter loop (float32 tolerance)."""
    cfg = small_cfg()
    batch = real_batch(tiny_dataset, cfg)
    fast = init_model(cfg)
    plain = copy.deepcopy(fast)
    opt_fast = torch.optim.AdamW(fast.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay, foreach=True)
    opt_plain = torch.optim.AdamW(plain.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay, foreach=False)
    dev = torch.device("cpu")
    for step in range(2):
        terms = _train_step(fast, fast, opt_fast, batch, cfg, step, dev, False)
        out = plain(batch["image"])
        logits = plain.line_logits(out["features"], batch["segments_px"])
        ref = indexed_losses(out, batch, logits, cfg.loss, 4)
        opt_plain.zero_grad()
        ref["loss"].backward()
        torch.nn.utils.clip_grad_norm_(plain.parameters(), 10.0, foreach=False)
        opt_plain.step()
        want = float(ref["loss"].detach())
        assert abs(float(terms["loss"]) - want) < 1e-5 * max(1.0, abs(want))
    for (name, a), b in zip(fast.state_dict().items(), plain.state_dict().values()):
        assert torch.allclose(a.float(), b.float(), rtol=1e-4, atol=1e-6), name


def test_bf16_step_loss_within_bf16_tolerance_of_float32(tiny_dataset):
    cfg = small_cfg()
    batch = real_batch(tiny_dataset, cfg)
    model = init_model(cfg)
    with torch.no_grad():
        out32 = model(batch["image"])
        with torch.autocast("cpu", dtype=torch.bfloat16):
            out16 = model(batch["image"])
        logits32 = model.line_logits(out32["features"], batch["segments_px"])
        logits16 = model.line_logits(out16["features"].float(), batch["segments_px"])
        l32 = corner_losses(out32, batch, logits32, cfg.loss, 4)["loss"]
        l16 = corner_losses({k: v.float() for k, v in out16.items()}, batch, logits16, cfg.loss, 4)["loss"]
    assert abs(float(l16) - float(l32)) < 0.02 * abs(float(l32))
