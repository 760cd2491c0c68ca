"""Corruption: severity 0 leaves the image unchanged; each kind at a higher level changes it as it should;
parameters are drawn from the sample's Generator only."""

import json

import numpy as np
import pytest

from envisat_pose.datagen.corrupt import KINDS, apply_corruption, draw_corruption
from envisat_pose.datagen.image_kernels import motion_kernel
from envisat_pose.datagen.shards import decode_png


def make_image():
    rng = np.random.default_rng(0)
    img = np.zeros((128, 128), np.uint8)
    img[40:90, 30:100] = 180
    img[60:70, 50:60] = 250
    return img + rng.integers(0, 3, img.shape).astype(np.uint8)


def levels(**kw):
    lv = {k: "none" for k in KINDS}
    lv.update(kw)
    return lv


def test_severity_zero_is_identity():
    img = make_image()
    for seed in range(5):
        params = draw_corruption(levels(), 128, np.random.default_rng(seed))
        out = apply_corruption(img, params)
        assert np.array_equal(out, img)
        assert params["exposure_gain"] == 1.0 and params["gaussian_noise_sigma"] == 0.0
        assert params["shot_noise_full_well_e"] is None and params["gaussian_blur_sigma_px"] == 0.0


@pytest.mark.parametrize("kind", KINDS)
def test_each_kind_changes_the_image(kind):
    img = make_image()
    params = draw_corruption(levels(**{kind: "high"}), 128, np.random.default_rng(1))
    out = apply_corruption(img, params)
    assert not np.array_equal(out, img)
    diff = out.astype(float) - img
    if kind == "gaussian_noise":
        assert abs(diff[42:58, 32:100].std() - 10.0) < 1.0  # sigma 10 grey levels on a flat grey patch
    if kind == "shot_noise":
        # variance = signal x 255 / full well: much noisier on the bright patch than on the dark one
        assert diff[45:85, 35:95].std() > 3 * diff[5:30, 5:30].std()
    if kind in ("gaussian_blur", "motion_blur"):
        assert abs(out.astype(float).mean() - img.mean()) < 1.0  # blur keeps the energy
        assert out[40:90, 30:100].std() < img[40:90, 30:100].std() or out[39, 60] > img[39, 60]


def test_same_seed_same_params_and_pixels():
    img = make_image()
    mixed = {k: "mixed" for k in KINDS}
    a = draw_corruption(mixed, 128, np.random.default_rng(42))
    b = draw_corruption(mixed, 128, np.random.default_rng(42))
    assert a == b
    assert np.array_equal(apply_corruption(img, a), apply_corruption(img, b))
    c = draw_corruption(mixed, 128, np.random.default_rng(43))
    assert c != a


def test_motion_kernel_is_a_normalised_streak():
    k = motion_kernel(9.0, 0.0)
    assert k.shape == (11, 11) and abs(k.sum() - 1) < 1e-6
    assert np.all(k[np.arange(11) != 5] == 0)  # horizontal streak: one row
    k = motion_kernel(9.0, 90.0)
    assert np.allclose(k[:, 5].sum(), 1.0, atol=1e-6)


def test_blurring_only_the_content_box_equals_blurring_the_whole_frame():
    """apply_corruption blurs the box around the non-black pixels; the whole frame gives the same image."""
    import cv2

    img = np.zeros((256, 256), np.uint8)
    img[100:140, 60:200] = 170
    img[110:118, 90:96] = 250
    for seed in range(6):
        params = draw_corruption(levels(motion_blur="high", gaussian_blur="high", exposure="medium"), 1024,
                                 np.random.default_rng(seed))
        out = apply_corruption(img, params)
        full = img.astype(np.float32) * np.float32(params["exposure_gain"])
        full = cv2.filter2D(full, -1, motion_kernel(params["motion_blur_length_px"], params["motion_blur_angle_deg"]),
                            borderType=cv2.BORDER_REFLECT)
        full = cv2.GaussianBlur(full, (0, 0), params["gaussian_blur_sigma_px"], borderType=cv2.BORDER_REFLECT)
        ref = np.clip(np.rint(full), 0, 255).astype(np.uint8)
        assert np.abs(out.astype(int) - ref).max() <= 1  # float round-off may flip a x.5 pixel
        assert np.mean(out != ref) < 1e-3
        assert (out > 0).sum() > (img > 0).sum()  # the blur really spread the content
    # content touching the image border: the border reflection is the same either way
    edge = np.zeros((128, 128), np.uint8)
    edge[0:20, 0:30] = 200
    params = draw_corruption(levels(gaussian_blur="high"), 1024, np.random.default_rng(0))
    ref = np.clip(np.rint(cv2.GaussianBlur(edge.astype(np.float32), (0, 0), params["gaussian_blur_sigma_px"],
                                           borderType=cv2.BORDER_REFLECT)), 0, 255).astype(np.uint8)
    assert np.abs(apply_corruption(edge, params).astype(int) - ref).max() <= 1


def _generate(tmp_path, name, **kw):
    from envisat_pose.config import from_dict
    from envisat_pose.datagen.factory import run_generate
    from envisat_pose.datagen.generate_config import GenerateConfig
    from envisat_pose.shard_reader import read_shard

    base = {"num_images": 2, "shard_size": 2, "resolution_px": 96, "seed": 11}
    base.update(kw)
    out = tmp_path / name
    manifest = run_generate(from_dict(GenerateConfig, base), str(out))
    return list(read_shard(str(out / manifest["shards"][0]["name"])))


def test_sensor_model_with_every_kind_none_gives_uncorrupted_frames(tmp_path):
    """Issue 17 item 6: model 'sensor' with all five kinds 'none' stores the clean render (the same bytes as
    storage 'clean'), and differs from the space camera's default frames."""
    off = {"model": "sensor", **{k: "none" for k in KINDS}}
    stored = _generate(tmp_path, "off", corruption=off)
    clean = _generate(tmp_path, "clean", corruption=off, storage="clean")
    noisy = _generate(tmp_path, "noisy")
    for (key_a, a), (key_b, b), (_, c) in zip(stored, clean, noisy):
        assert key_a == key_b and a["png"] == b["png"]
        assert a["png"] != c["png"]  # the default space camera does corrupt
        lab = json.loads(a["json"])
        assert lab["corruption"]["model"] == "none" and set(lab["corruption"]["levels"].values()) == {"none"}
        img = decode_png(b["png"])
        assert np.array_equal(apply_corruption(img, lab["corruption"]), img)


@pytest.mark.parametrize("kind,value", [("gaussian_noise", "none"), ("motion_blur", "high")])
def test_sensor_model_refuses_severities_it_would_ignore(kind, value):
    """Any severity but 'mixed' (or all 'none') under model 'sensor' is a one-line ConfigError naming the key
    and which model honours it."""
    from envisat_pose.config import ConfigError, from_dict
    from envisat_pose.datagen.generate_config import GenerateConfig

    with pytest.raises(ConfigError) as err:
        from_dict(GenerateConfig, {"corruption": {"model": "sensor", kind: value}})
    msg = str(err.value)
    assert "\n" not in msg and f"corruption.{kind}" in msg and "'paper'" in msg
    from_dict(GenerateConfig, {"corruption": {"model": "paper", kind: value}})  # the paper model honours it
