"""Online training data (pipelines/detector/online.py): the frames are the factory's samples, the schedule crops no frame
more than K times, the batches repeat for a seed whatever the worker count, a stopped run resumes after what it
trained, and the label statistics match the offline path's."""

import json
import multiprocessing
import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import numpy as np
import pytest
import torch

from envisat_pose.datagen.generate_config import AppearanceConfig, GenerateConfig, SequenceModeConfig
from envisat_pose.perception.data import DataConfig
from envisat_pose.pipelines.detector.online import online_batches, uses_before, window_start
from envisat_pose.pipelines.detector.render_pool import FRAME_STAGES, RenderPool

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
    with RenderPool(cfg, 1, 2) as source:  # from frame 2: a resumed run renders no earlier frame
        for f in range(2, 6):
            frame, corners, visible, in_frame, side = source.take(image)
            _, want_image, want = offline[f]
            assert frame == f and side == 128 and np.array_equal(image, want_image)
            assert np.array_equal(corners, want["corners_px"]) and np.array_equal(visible, want["visible"])
            assert np.array_equal(in_frame, want["in_frame"])
    assert not multiprocessing.active_children()


def standing(state: dict) -> dict:
    """Where an online run stands: its state without what it measured (frame_ms, a wall time)."""
    return {k: v for k, v in state.items() if k != "frame_ms"}


def test_batches_repeat_and_a_stopped_run_resumes_after_what_it_trained():
    kw = dict(seed=5, batch_size=4, workers=1, device="cpu", uses_per_frame=2)
    run = take(4, **kw)
    states = [json.loads(json.dumps(state)) for _, state in run]  # JSON-able, as a run folder keeps it
    resumed = take(2, **kw, start_state=states[1])
    for (a, _), (b, state) in zip(run[2:], resumed):
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert standing(resumed[-1][1]) == standing(states[3])
    assert set(states[3]["frame_ms"]) == set(FRAME_STAGES) and all(v > 0 for v in states[3]["frame_ms"].values())
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
        assert all(torch.equal(a[k], b[k]) for k in a) and standing(sa) == standing(sb)


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


def test_a_mix_deals_its_frames_by_weight_and_its_file_reads_back(tmp_path):
    """Each look gets its rounded share of every LOOK_PERIOD frames, spread over the period, and its samples
    0, 1, 2, ... in frame order; the looks file round-trips and bad files name the field."""
    from envisat_pose.config import ConfigError
    from envisat_pose.pipelines.detector import look_mix

    WeightedLook, LOOK_PERIOD = look_mix.WeightedLook, look_mix.LOOK_PERIOD
    looks = (WeightedLook("big", GEN, 2000.0), WeightedLook("mid", GEN, 800.0), WeightedLook("tiny", GEN, 1.0),
             WeightedLook("seq", GenerateConfig(mode="sequence", sequence=SequenceModeConfig("slow-tumble"), resolution_px=96, num_images=7,
                                        **CHEAP), 300.0))
    shares = look_mix.look_shares(looks)
    assert shares.sum() == LOOK_PERIOD and shares.tolist() == [64, 26, 1, 9]  # 64.5 / 25.8 / 0.03 / 9.7, tiny >= 1
    pattern = look_mix.look_pattern(shares)
    samples = [[] for _ in looks]
    first_period = []
    for f in range(3 * LOOK_PERIOD):
        j, i = look_mix.frame_look(f, shares, pattern)
        samples[j].append(i)
        if f < LOOK_PERIOD:
            first_period.append(j)
    assert [s == list(range(3 * n)) for s, n in zip(samples, shares)] == [True] * 4
    gaps = np.diff([f for f, j in enumerate(first_period) if j == 1])
    assert gaps.max() <= 5  # 'mid' every ~3.8 frames, not in one block
    path = tmp_path / "looks.toml"
    path.write_text(look_mix.looks_toml(looks))
    assert look_mix.read_looks(str(path)) == looks
    path.write_text('seed = 5\n[[look]]\nname = "a"\nweight = 2\n[[look]]\nname = "b"\nresolution_px = 64\n')
    a, b = look_mix.read_looks(str(path))
    assert (a.generate.seed, b.generate.seed, b.generate.resolution_px, a.weight, b.weight) == (5, 5, 64, 2, 1.0)
    for text, field in [('[[look]]\nweight = 1\n', "look[0].name"), ("seed = 1\n", "look"),
                        ('[[look]]\nname = "a"\nweight = -1\n', "looks.a.weight"),
                        ('[[look]]\nname = "a"\n[look.random]\nrange_min_m = "x"\n', "look.a.random.range_min_m"),
                        ('[[look]]\nname = "a"\nrange_min_m = 30\n', "look.a.range_min_m: moved to look.a.random.range_min_m"),
                        ('[[look]]\nname = "a"\n[[look]]\nname = "a"\n', "looks")]:
        path.write_text(text)
        with pytest.raises(ConfigError, match=field.replace(".", r"\.").replace("[", r"\[")):
            look_mix.read_looks(str(path))


@pytest.mark.slow  # renders two looks at two sizes (~10 s)
def test_a_mix_of_sizes_and_scenarios_renders_each_looks_own_frames(tmp_path):
    """A random look at 128 px and a sequence look at 96 px: each frame is its look's sample (the random look's
    dataset sample, the sequence's frame as `envisat generate` writes that sequence), the smaller one top-left in
    the slot with zeros beyond; the batches crop each frame within its own size."""
    from envisat_pose.datagen.factory import generate_shard
    from envisat_pose.perception.data import read_samples
    from envisat_pose.pipelines.detector.look_mix import (
        WeightedLook,
        frame_look,
        look_pattern,
        look_shares,
        sequence_seed,
    )

    seq_cfg = GenerateConfig(mode="sequence", sequence=SequenceModeConfig("slow-tumble", 5.0), resolution_px=96,
                             num_images=4, shard_size=4, seed=12, **CHEAP)
    looks = (WeightedLook("random", GEN, 1.0), WeightedLook("seq", seq_cfg, 1.0))
    shares = look_shares(looks)
    pattern = look_pattern(shares)
    want_seq = {}
    for q in range(2):  # the look's sequences 0 and 1, as `envisat generate` writes them
        cfg_q = GenerateConfig(**{**seq_cfg.__dict__, "seed": sequence_seed(seq_cfg.seed, q)})
        folder = tmp_path / f"seq{q}"
        folder.mkdir()
        name = generate_shard(cfg_q, 0, str(folder))["name"]
        for k, (_, image, label) in enumerate(read_samples([str(folder / name)])):
            want_seq[q * 4 + k] = (image, label)
    rnd = tmp_path / "random"
    rnd.mkdir()
    want_rnd = [s[1:] for s in read_samples([str(rnd / generate_shard(GEN, i, str(rnd))["name"]) for i in (0, 1)])]
    image = np.zeros((128, 128), np.uint8)
    seen = set()
    with RenderPool(looks, 2, 0) as source:
        for f in range(12):
            frame, corners, visible, in_frame, side = source.take(image)
            j, i = frame_look(f, shares, pattern)
            seen.add(j)
            want_image, want = (want_rnd if j == 0 else want_seq)[i]
            assert frame == f and side == (128 if j == 0 else 96)
            assert np.array_equal(image[:side, :side], want_image) and not image[side:].any()
            assert not image[:, side:].any()
            assert np.array_equal(corners, want["corners_px"]) and np.array_equal(visible, want["visible"])
    assert seen == {0, 1}
    it = online_batches(looks, DATA, seed=3, batch_size=8, workers=1, device="cpu", uses_per_frame=2)
    try:
        for _ in range(3):
            batch, _ = next(it)
            frames = batch["sample_id"][:, 0].tolist()
            small = torch.tensor([frame_look(f, shares, pattern)[0] == 1 for f in frames])
            box = batch["crop_px"]
            whole = (box[:, 0] == 0) & (box[:, 1] == 0) & (box[:, 2] >= 96)
            assert (box[small & whole, 2] == 96).all() and (box[~small & whole, 2] == 128).all()
    finally:
        it.close()
    assert not multiprocessing.active_children()


def test_each_ddp_rank_renders_its_own_frames_under_one_state():
    """Rank 0 (stream 0) is a single process's run, bit for bit; rank 1's frames and crops differ from it (every
    rank rendered the same frames, so a second rank added only its count), and its state is the same one, which
    rank 0 writes and every rank resumes from."""
    kw = dict(seed=3, batch_size=2, workers=1, device="cpu", uses_per_frame=2)
    plain, rank0, rank1 = take(2, **kw), take(2, **kw, stream=0), take(2, **kw, stream=1)
    def state(s):
        return {k: v for k, v in s.items() if k != "frame_ms"}  # frame_ms: this session's timing

    for (a, sa), (b, sb), (c, sc) in zip(plain, rank0, rank1):
        assert all(torch.equal(a[key], b[key]) for key in a) and state(sa) == state(sb) == state(sc)
        assert not torch.equal(a["image"], c["image"])
