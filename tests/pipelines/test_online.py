"""Online training data (pipelines/online.py): the frames are the factory's samples, the schedule crops no frame
more than K times, the batches repeat for a seed whatever the worker count, a stopped run resumes after what it
trained, and the label statistics match the offline path's."""

import json
import multiprocessing
import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import numpy as np
import pytest
import torch

from envisat_pose.datagen.generate_config import AppearanceConfig, GenerateConfig
from envisat_pose.perception.data import DataConfig
from envisat_pose.pipelines.online import FrameSource, online_batches, uses_before, window_start

# the fast tests' looks: one texture per class and no Earth (its textures take seconds to make at first use);
# the slow statistics test renders the default looks
CHEAP = dict(earth_probability=0.0, appearance=AppearanceConfig(texture_set_size=1))
GEN = GenerateConfig(resolution_px=128, seed=31, shard_size=5, **CHEAP)
DATA = DataConfig(input_px=64)


def take(n_steps, **kw):
    """The first n_steps (batch, state) pairs of an online run (CPU tensors), its workers ended after."""
    it = online_batches(GEN, DATA, **kw)
    try:
        return [next(it) for _ in range(n_steps)]
    finally:
        it.close()


@pytest.mark.parametrize("n, k", [(4, 2), (16, 8), (5, 3), (3, 8), (64, 7)])
def test_schedule_crops_every_frame_at_most_k_times(n, k):
    uses = {}
    for step in range(60):
        f0 = window_start(step, n, k)
        for f in range(f0, f0 + n):
            assert uses_before(f, step, n, k) == uses.get(f, 0)
            uses[f] = uses.get(f, 0) + 1
    settled = [u for f, u in uses.items() if n <= f < window_start(60 - k, n, k)]
    assert max(uses.values()) == k and min(settled) == k  # past the first window, exactly K crops each


def test_frames_are_the_factory_samples(tmp_path):
    """Frame f of the online source is sample f of `envisat generate` with the same config: pixels and labels."""
    from envisat_pose.datagen.factory import generate_shard
    from envisat_pose.perception.data import read_samples

    cfg = GenerateConfig(resolution_px=128, seed=31, shard_size=3, num_images=6, **CHEAP)
    paths = [generate_shard(cfg, i, str(tmp_path))["name"] for i in range(2)]
    offline = list(read_samples([str(tmp_path / p) for p in paths]))
    image = np.zeros((128, 128), np.uint8)
    with FrameSource(cfg, 1, 2) as source:  # from frame 2: a resumed run renders no earlier frame
        for f in range(2, 6):
            frame, corners, visible, in_frame = source.take(image)
            _, want_image, want = offline[f]
            assert frame == f and np.array_equal(image, want_image)
            assert np.array_equal(corners, want["corners_px"]) and np.array_equal(visible, want["visible"])
            assert np.array_equal(in_frame, want["in_frame"])
    assert not multiprocessing.active_children()


def test_batches_repeat_and_a_stopped_run_resumes_after_what_it_trained():
    kw = dict(seed=5, batch_size=4, workers=1, device="cpu", uses_per_frame=2)
    run = take(4, **kw)
    states = [json.loads(json.dumps(state)) for _, state in run]  # JSON-able, as a run folder keeps it
    resumed = take(2, **kw, start_state=states[1])
    for (a, _), (b, state) in zip(run[2:], resumed):
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert resumed[-1][1] == states[3]
    # the resumed run's first window starts where the state says and continues each frame's count
    first = resumed[0][0]["sample_id"]
    assert int(first[:, 0].min()) == states[1]["next_frame"] == 4
    assert first[:, 1].tolist() == [1, 1, 0, 0]
    # no frame cropped more than K times, and the run records it
    frames = torch.cat([b["sample_id"][:, 0] for b, _ in run]).tolist()
    assert max(frames.count(f) for f in set(frames)) == 2 == states[-1]["max_uses"]
    batch = run[0][0]
    assert batch["image"].shape == (4, 1, 64, 64) and batch["jmap"].shape == (4, 4, 16, 16)
    assert batch["valid"].dtype == torch.bool and batch["crop_px"].shape == (4, 3)
    with pytest.raises(ValueError, match="uses_per_frame"):
        take(1, **dict(kw, uses_per_frame=3), start_state=states[1])
    assert not multiprocessing.active_children()


@pytest.mark.slow
def test_two_workers_give_the_batches_of_one():
    kw = dict(seed=6, batch_size=4, device="cpu", uses_per_frame=4)
    one, two = take(3, workers=1, **kw), take(3, workers=2, **kw)
    for (a, sa), (b, sb) in zip(one, two):
        assert all(torch.equal(a[k], b[k]) for k in a) and sa == sb


@pytest.mark.slow
def test_online_and_offline_label_statistics_agree(tmp_path):
    """The same looks, offline (make_sample over the factory's shards, K crops a frame) and online (the batched
    path over the same frames): visible-corner share, corner positions, crop sizes and the whole-frame share agree
    within sampling error."""
    from envisat_pose.datagen.factory import generate_shard
    from envisat_pose.perception.data import make_sample, read_samples

    n_frames, k = 60, 4
    cfg = GenerateConfig(resolution_px=256, seed=41, shard_size=20, num_images=n_frames)
    data = DataConfig(input_px=96)
    paths = [str(tmp_path / generate_shard(cfg, i, str(tmp_path))["name"]) for i in range(cfg.num_shards)]
    offline = []
    for f, (_, image, label) in enumerate(read_samples(paths)):
        for j in range(k):
            s = make_sample(image, label, data, np.random.default_rng([77, f, j]))
            offline.append({key: s[key] for key in ("corners_px", "valid", "crop_px")})
    online = []
    it = online_batches(cfg, data, seed=78, batch_size=8, workers=1, device="cpu", uses_per_frame=k)
    try:
        while len(online) < len(offline):
            batch, _ = next(it)
            for n in range(8):
                online.append({key: batch[key][n].numpy() for key in ("corners_px", "valid", "crop_px")})
    finally:
        it.close()

    def stats(samples):
        valid = np.array([s["valid"] for s in samples])
        pts = np.concatenate([s["corners_px"][s["valid"]] for s in samples])
        side = np.array([s["crop_px"][2] for s in samples])
        whole = np.array([s["crop_px"][2] == 256 and s["crop_px"][0] == 0 and s["crop_px"][1] == 0
                          for s in samples])
        return {"valid share": (valid.mean(1), None), "corner x": (pts[:, 0], None), "corner y": (pts[:, 1], None),
                "crop side": (side[~whole], None), "whole share": (whole.astype(float), None)}

    a, b = stats(offline), stats(online)
    for name in a:
        x, y = a[name][0], b[name][0]
        se = np.sqrt(x.var() / len(x) + y.var() / len(y))
        assert abs(x.mean() - y.mean()) < 4 * se + 1e-9, (name, x.mean(), y.mean(), se)
