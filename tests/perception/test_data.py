"""Samples from shards: shapes, labels mapped into the crop, determinism, clear errors for bad inputs."""

import io
import json
import tarfile

import cv2
import numpy as np
import pytest

from envisat_pose.config import InputError
from envisat_pose.perception.data import DataConfig, make_sample, read_samples, shard_paths, to_full_px, to_input_px
from envisat_pose.perception.heatmaps import decode_junctions
from envisat_pose.perception.stream import epoch_loader, shard_samples


def _write_shard(path, samples):
    with tarfile.open(path, "w") as tar:
        for key, members in samples:
            for suffix, data in members.items():
                info = tarfile.TarInfo(f"{key}.{suffix}")
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))


def _label():
    return json.dumps({"corners_px": [[10.0, 10.0]] * 8, "visible": [True] * 8, "in_frame": [True] * 8,
                       "K": np.eye(3).tolist(), "scene": {"new": "keys are ignored"}}).encode()


def _png(image):
    return cv2.imencode(".png", image)[1].tobytes()


def test_samples_have_documented_shapes_and_targets(tiny_dataset):
    cfg = DataConfig(input_px=128, augment=False, crop_scale_jitter=0, crop_shift_jitter=0)
    samples = [make_sample(image, label, cfg, None) for _, image, label in read_samples(shard_paths(tiny_dataset))]
    assert len(samples) == 8
    labels = [lab for _, _, lab in read_samples(shard_paths(tiny_dataset))]
    checked = 0
    for s, lab in zip(samples, labels):
        assert s["image"].shape == (1, 128, 128) and s["image"].dtype == np.float32
        assert s["jmap"].shape == (4, 32, 32) and s["joff"].shape == (2, 32, 32) and s["jmask"].shape == (32, 32)
        assert s["segments_px"].shape == (32, 2, 2)
        # the crop maps back to the label's pixels
        assert np.allclose(to_full_px(s["corners_px"], s["crop_px"], 128), lab["corners_px"], atol=1e-3)
        # targets decode to the valid corners
        d = decode_junctions(s["jmap"], s["joff"], 4, top_k=16, threshold=0.99)
        want = s["corners_px"][s["valid"]]
        if len(want) and len(d["points_px"]) == len(want):
            dist = np.linalg.norm(d["points_px"][:, None] - want[None], axis=-1).min(axis=1)
            assert dist.max() < 0.05
            checked += 1
        # every box edge between two valid corners is a positive segment
        edges = {(0, 1), (1, 2), (2, 3), (0, 3), (4, 5), (5, 6), (6, 7), (4, 7), (0, 4), (1, 5), (2, 6), (3, 7)}
        n_edges = sum(1 for a, b in edges if s["valid"][a] and s["valid"][b])
        assert s["line_label"].sum() == n_edges
    assert checked >= 6


def test_crop_mapping_round_trip():
    box = np.array([100, 50, 300])
    p = np.random.default_rng(0).uniform(0, 400, size=(10, 2))
    assert np.allclose(to_full_px(to_input_px(p, box, 320), box, 320), p)


def test_augmentation_is_seeded(tiny_dataset):
    cfg = DataConfig(input_px=128)
    path = shard_paths(tiny_dataset)[0]
    a = list(shard_samples(path, 0, cfg, seed=5, epoch=1))
    b = list(shard_samples(path, 0, cfg, seed=5, epoch=1))
    c = list(shard_samples(path, 0, cfg, seed=6, epoch=1))
    d = list(shard_samples(path, 0, cfg, seed=5, epoch=2))
    assert all(np.array_equal(x["image"], y["image"]) for x, y in zip(a, b))
    assert not all(np.array_equal(x["image"], y["image"]) for x, y in zip(a, c))
    assert not all(np.array_equal(x["image"], y["image"]) for x, y in zip(a, d))


@pytest.mark.parametrize("members, message", [
    ({"png": b"this is not a png", "json": _label()}, "not an image"),
    ({"png": _png(np.zeros((8, 8, 3), np.uint8)), "json": _label()}, "3-channel"),
    ({"png": _png(np.zeros((8, 8), np.uint16)), "json": _label()}, "16-bit"),
    ({"txt": b"hello", "json": _label()}, "no '.png'"),
    ({"png": _png(np.zeros((8, 8), np.uint8)), "json": b"{}"}, "not a corner label"),
])
def test_bad_members_are_one_clear_error(tmp_path, members, message):
    _write_shard(tmp_path / "shard-000000.tar", [("000000000", members)])
    with pytest.raises(InputError, match=message) as err:
        list(shard_samples(shard_paths(str(tmp_path))[0], 0, DataConfig(input_px=64), 0, 0))
    assert "\n" not in str(err.value) and "000000000" in str(err.value)


def test_empty_dataset(tmp_path):
    with pytest.raises(InputError, match="empty dataset"):
        shard_paths(str(tmp_path))
    _write_shard(tmp_path / "shard-000000.tar", [])
    assert list(epoch_loader(shard_paths(str(tmp_path)), DataConfig(input_px=64), 0, 0, 1, 0)) == []
    from envisat_pose.perception.model import ModelConfig
    from envisat_pose.perception.train import TrainConfig, train

    cfg = TrainConfig(steps=1, batch_size=1, model=ModelConfig(input_px=64, width=16, depth=2, stem_width=8),
                      data=DataConfig(input_px=64))
    with pytest.raises(InputError, match="fewer samples than one batch"):
        train(cfg, str(tmp_path), str(tmp_path / "run"), progress=False)
    with pytest.raises(InputError, match="no such folder"):
        shard_paths(str(tmp_path / "nope"))
