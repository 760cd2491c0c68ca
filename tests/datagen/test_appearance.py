"""Appearance, lighting, clutter and storage: appearance draws change pixels only; a half-turn about the long axis stays
visible; clutter has its own mask value and hides corners; clean storage corrupted on read gives the corrupted
storage's bytes; same seed, same bytes with appearance and clutter on."""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import json

import numpy as np
import pytest

from envisat_pose.config import from_dict
from envisat_pose.datagen.appearance import GEOM_CLASS, class_texture
from envisat_pose.datagen.factory import run_generate, view_from_scene, with_appearance
from envisat_pose.datagen.generate_config import GenerateConfig
from envisat_pose.datagen.render import SceneRenderer
from envisat_pose.datagen.render_view import APPENDAGE_MASK_VALUE, View
from envisat_pose.shard_reader import read_shard

RES = 256


def cfg_of(**kw):
    base = {"num_images": 4, "shard_size": 2, "resolution_px": 160, "seed": 11}
    base.update(kw)
    return from_dict(GenerateConfig, base)


def samples(out, manifest):
    return [(k, m) for e in manifest["shards"] for k, m in read_shard(os.path.join(out, e["name"]))]


def strip(label):
    """A label without what appearance and storage are allowed to change."""
    return {k: v for k, v in label.items() if k not in ("scene", "image_stored")}


@pytest.fixture(scope="module")
def renderer():
    r = SceneRenderer(RES, texture_set_size=4)
    yield r
    r.close()


def test_textures_are_seeded_and_differ():
    a = class_texture(0, "mli_gold", 0)
    assert a.shape == (256, 256, 3) and a.dtype == np.uint8 and a.std() > 5
    assert np.array_equal(a, class_texture(0, "mli_gold", 0))
    assert not np.array_equal(a, class_texture(0, "mli_gold", 1))
    assert not np.array_equal(a, class_texture(1, "mli_gold", 0))


def test_appearance_changes_pixels_not_labels_masks_or_depth(tmp_path):
    """The same poses with appearance off, on, and on with another appearance seed: identical labels (scene
    aside), masks and depth; the images differ."""
    runs = {}
    for name, app in (("off", {"enabled": False}), ("on", {"enabled": True}), ("on2", {"enabled": True, "seed": 1})):
        cfg = cfg_of(appearance=app, storage="clean")
        out = str(tmp_path / name)
        runs[name] = samples(out, run_generate(cfg, out))
    for (ka, a), (kb, b), (kc, c) in zip(runs["off"], runs["on"], runs["on2"]):
        la, lb, lc = (json.loads(m["json"]) for m in (a, b, c))
        assert strip(la) == strip(lb) == strip(lc)
        assert a["mask.png"] == b["mask.png"] == c["mask.png"] and a["depth.png"] == b["depth.png"] == c["depth.png"]
        assert a["png"] != b["png"] and b["png"] != c["png"]
        assert lb["scene"]["look"]["materials"] != lc["scene"]["look"]["materials"]
        assert la["scene"]["look"]["materials"] == {}
        # every face keeps its covering class whatever the appearance draw
        assert {g: m["class"] for g, m in lb["scene"]["look"]["materials"].items()} == {
            g: GEOM_CLASS[g] for g in lb["scene"]["look"]["materials"]}
        assert lb["scene"]["face_classes"]["face_py"] != lb["scene"]["face_classes"]["face_my"]
        assert lb["scene"]["face_classes"]["face_pz"] != lb["scene"]["face_classes"]["face_mz"]


def half_turn_views(appearance):
    """A view of the body's side, and the same pose turned half a turn about the body's long axis (x_T)."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_euler("xyz", [35, 10, 80], degrees=True).as_matrix()
    flip = np.diag([1.0, -1.0, -1.0])  # half-turn about x_T
    rho = np.array([0.0, 30.0, 0.0])
    sun = np.array([0.2, -1.0, 0.3])
    return (View(rho, R, sun, appearance=appearance), View(rho, R @ flip, sun, appearance=appearance))


def test_half_turn_about_the_long_axis_is_visible(renderer):
    """Corners A<->C, B<->D, E<->G, F<->H trade places under the half-turn; the silhouette (mask of the body) is
    nearly the same, yet the image differs in every appearance draw because the faces' classes differ."""
    cfg = cfg_of(appearance={"texture_set_size": 4})
    base = View(np.zeros(3), np.eye(3), np.array([0.0, -1.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    n_checked = 0
    for seed in range(4):
        view, _ = with_appearance(cfg, base, {}, seed)
        a, b = (renderer.render(v) for v in half_turn_views(view.appearance))
        body_a, body_b = (a.mask_u8 >= 1) & (a.mask_u8 <= 6), (b.mask_u8 >= 1) & (b.mask_u8 <= 6)
        both = body_a & body_b
        assert both.sum() > 0.9 * body_a.sum() > 500  # the same silhouette of the box
        diff = np.abs(a.gray_u8[both].astype(float) - b.gray_u8[both].astype(float))
        # the faces in view swap classes (+y gold <-> -y black foil, +z silver foil <-> -z radiator tiles)
        assert np.mean(diff > 10) > 0.3, np.mean(diff > 10)
        n_checked += 1
    assert n_checked == 4


def test_clutter_has_its_own_mask_value_and_can_hide_corners(renderer):
    """The ASAR antenna stands 0.5 m off -z: seen from below at a slant, it hides body pixels and is mask 8;
    the box's corners and pose are unchanged by the switch."""
    from scipy.spatial.transform import Rotation

    from envisat_pose.datagen.labels import make_label

    d_T = np.array([0.25, 0.45, -1.0])
    d_T /= np.linalg.norm(d_T)
    R = Rotation.align_vectors([[0.0, -1.0, 0.0]], [d_T])[0].as_matrix()
    view = View(np.array([0.0, 28.0, 0.0]), R, np.array([0.0, -1.0, 0.0]))
    off = renderer.render(view)
    on = renderer.render(View(view.rho_C_m, R, view.sun_dir_C, appendages=True))
    assert np.count_nonzero(on.mask_u8 == APPENDAGE_MASK_VALUE) > 300
    assert not np.any(off.mask_u8 == APPENDAGE_MASK_VALUE)
    np.testing.assert_array_equal(on.corners_K_m, off.corners_K_m)
    hidden = (off.mask_u8 == 6) & (on.mask_u8 == APPENDAGE_MASK_VALUE)  # -z face behind the antenna
    assert hidden.sum() > 200
    assert np.all(on.depth_m[hidden] < off.depth_m[hidden])
    from envisat_pose.target import load_target

    target = load_target()
    lab_off = make_label(off.corners_K_m, target.visible(off.R_K_from_T, off.t_K_from_T_m), renderer.K,
                         off.R_K_from_T, off.t_K_from_T_m, np.zeros(12), 0.002, {}, 0, {})
    lab_on = make_label(on.corners_K_m, target.visible(on.R_K_from_T, on.t_K_from_T_m, True), renderer.K,
                        on.R_K_from_T, on.t_K_from_T_m, np.zeros(12), 0.002, {}, 0, {})
    assert lab_on["corners_px"] == lab_off["corners_px"]


def test_clean_storage_corrupted_on_read_is_byte_identical(tmp_path):
    from envisat_pose.datagen.dataset import sample_png

    out_c, out_k = str(tmp_path / "clean"), str(tmp_path / "corrupted")
    clean = samples(out_c, run_generate(cfg_of(storage="clean"), out_c))
    corrupted = samples(out_k, run_generate(cfg_of(storage="corrupted"), out_k))
    n_changed = 0
    for (ka, a), (kb, b) in zip(clean, corrupted):
        la, lb = json.loads(a["json"]), json.loads(b["json"])
        assert la["image_stored"] == "clean" and lb["image_stored"] == "corrupted"
        assert strip(la) == strip(lb) and la["scene"] == lb["scene"]
        assert sample_png(a) == b["png"]
        assert sample_png(b) == b["png"]
        n_changed += a["png"] != b["png"]
        assert len(a["png"]) < len(b["png"])  # the clean render compresses better
    assert n_changed == len(clean)


def test_same_seed_same_bytes_with_appearance_and_clutter(tmp_path):
    cfg = cfg_of(earth_probability=0.5)
    assert cfg.appearance_on and cfg.appendages_on
    a = run_generate(cfg, str(tmp_path / "a"))
    b = run_generate(cfg, str(tmp_path / "b"), workers=2)
    assert [e["sha256"] for e in a["shards"]] == [e["sha256"] for e in b["shards"]]
    c = run_generate(cfg_of(earth_probability=0.5, appearance={"seed": 3}), str(tmp_path / "c"))
    assert [e["sha256"] for e in a["shards"]] != [e["sha256"] for e in c["shards"]]


def test_label_scene_rerenders_the_clean_image(tmp_path, renderer):
    from envisat_pose.datagen.shards import decode_png

    cfg = cfg_of(storage="clean", resolution_px=RES, appearance={"texture_set_size": 4}, earth_probability=1.0)
    out = str(tmp_path / "ds")
    for _, m in samples(out, run_generate(cfg, out)):
        lab = json.loads(m["json"])
        assert lab["scene"]["earthshine"]["intensity"] >= 0 and "sun_intensity" in lab["scene"]["look"]
        again = renderer.render(view_from_scene(lab["scene"]))
        assert np.array_equal(again.gray_u8, decode_png(m["png"]))
        assert np.array_equal(again.mask_u8, decode_png(m["mask.png"]))


def test_earthshine_lights_the_night_side(renderer):
    """With the sun behind the target (its near faces in shadow), Earth-shine from the camera's side brightens
    them; the mask is unchanged."""
    from envisat_pose.datagen.appearance import Appearance

    R = np.eye(3)
    rho = np.array([0.0, 30.0, 0.0])
    dark = renderer.render(View(rho, R, np.array([0.0, 1.0, 0.0]), np.array([0.0, -1.0, 0.2]),
                                appearance=Appearance({}, 1.2, 0.0), earth_backdrop=False))
    shine = renderer.render(View(rho, R, np.array([0.0, 1.0, 0.0]), np.array([0.0, -1.0, 0.2]),
                                 appearance=Appearance({}, 1.2, 0.3), earth_backdrop=False))
    body = (dark.mask_u8 >= 1) & (dark.mask_u8 <= 6)
    assert np.array_equal(dark.mask_u8, shine.mask_u8)
    assert shine.gray_u8[body].mean() > dark.gray_u8[body].mean() + 10


@pytest.mark.parametrize("key, value, message", [
    ("appearance", {"texture_set_size": 0}, "appearance.texture_set_size = 0"),
    ("appearance", {"specular": [0.9, 0.1]}, "appearance.specular = [0.9, 0.1]"),
    ("storage", "zip", "storage = 'zip'"),
    ("corruption", {"sensor": {"adc_bits": [7]}}, "corruption.sensor.adc_bits = [7]"),
])
def test_bad_appearance_or_camera_config_is_one_named_error(key, value, message):
    from envisat_pose.config import ConfigError

    with pytest.raises(ConfigError) as err:
        cfg_of(**{key: value})
    assert message in str(err.value)


def test_one_covering_draws_every_face_in_that_class(tmp_path):
    """appearance.one_covering: every face of the body in one class (labels, masks and depth unchanged, pixels
    not); an unknown class is a one-line error naming the field."""
    from envisat_pose.config import ConfigError

    runs = {}
    for name, app in (("own", {}), ("one", {"one_covering": "radiator"})):
        out = str(tmp_path / name)
        runs[name] = samples(out, run_generate(cfg_of(appearance=app, appendages=False, storage="clean"), out))
    for (_, a), (_, b) in zip(runs["own"], runs["one"]):
        la, lb = json.loads(a["json"]), json.loads(b["json"])
        assert strip(la) == strip(lb) and a["mask.png"] == b["mask.png"] and a["png"] != b["png"]
        faces = {g: m["class"] for g, m in lb["scene"]["look"]["materials"].items() if g.startswith("face_")}
        assert len(faces) == 6 and set(faces.values()) == {"radiator"} == set(lb["scene"]["face_classes"].values())
    with pytest.raises(ConfigError, match="one_covering"):
        cfg_of(appearance={"one_covering": "chrome"}).validate()
