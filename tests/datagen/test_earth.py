"""The Earth behind the target: drawn at the disc size and direction the geometry predicts (angular radius
asin(R / r) about the nadir, a closed form), lit by the sun (the terminator), never over the target, the mask
and depth untouched, labels equal with and without it, seeded (same seed, same bytes)."""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import json
import math

import cv2
import numpy as np
import pytest

from envisat_pose.datagen import earth
from envisat_pose.datagen.render import SceneRenderer
from envisat_pose.datagen.render_view import View
from envisat_pose.datagen.scenario import EARTH_RADIUS_M

RES = 160


@pytest.fixture(scope="module")
def renderer():
    r = SceneRenderer(RES)
    yield r
    r.close()


def unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def predicted_disc(K, nadir_K, r_m):
    """Closed form: the pixels whose centre ray is within asin(R / r) of the nadir; and the angle margin."""
    n = K.shape[0]
    u, v = np.meshgrid(np.arange(RES, dtype=float), np.arange(RES, dtype=float))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    angle = np.arccos(np.clip(rays @ unit(nadir_K), -1.0, 1.0))
    return angle, math.asin(EARTH_RADIUS_M / r_m), n


def emissive_earth(renderer):
    """Make the Earth's materials glow (emission 1): every pixel of the disc shows, lit or not."""
    m = renderer.model
    saved = m.mat_emission.copy()
    for i in renderer._earth_matid.values():
        m.mat_emission[i] = 1.0
    return saved




@pytest.mark.parametrize("r_m,off_deg,facing", [(30000e3, 8.0, False), (42164e3, 0.0, False),
                                                (7142e3, 55.0, False), (6878e3, 62.0, False),
                                                (7142e3, 55.0, True), (7378e3, 50.0, True), (6978e3, 52.0, True)])
def test_disc_at_the_predicted_size_and_direction(renderer, r_m, off_deg, facing):
    """The drawn disc equals the closed-form cone (angular radius asin(R / r) about the nadir) to within the
    one-pixel band of the antialiased limb, far (GEO: the whole disc in the frame) and near (LEO: the limb
    crossing the image), on the globe's mesh and on the detailed cap's (facing: the Earth turned as random
    mode turns it)."""
    from envisat_pose.attitude import rotmat_to_quat

    R_K_from_C = renderer._R_K_from_C
    a = math.radians(off_deg)
    nadir_K = np.array([math.sin(a) * 0.6, math.sin(a) * 0.8, math.cos(a)])
    rng = np.random.default_rng(3)
    quat = rotmat_to_quat(R_K_from_C.T @ earth.facing_attitude(-nadir_K, rng)) if facing else \
        earth.random_rotation_quat(rng)
    assert earth.cap_visible(quat, R_K_from_C.T @ nadir_K, r_m) == facing
    saved = emissive_earth(renderer)
    try:
        # the target behind the camera: nothing but the Earth in the image
        view = View(np.array([0.0, -60.0, 0.0]), np.eye(3), R_K_from_C.T @ -nadir_K, R_K_from_C.T @ nadir_K, r_m,
                    earth_quat_C=quat)
        out = renderer.render(view)
        assert (renderer.model.geom_dataid[renderer.earth_geom] == renderer._earth_cap_mesh) == facing
    finally:
        renderer.model.mat_emission[:] = saved
    angle, rho, _ = predicted_disc(renderer.K, nadir_K, r_m)
    drawn = out.gray_u8 > 2
    px_rad = 1.0 / renderer.K[0, 0]
    inside, outside = angle < rho - 1.5 * px_rad, angle > rho + 1.5 * px_rad
    assert inside.any() and outside.any()
    assert drawn[inside].all(), f"{(~drawn[inside]).sum()} disc pixels not drawn"
    assert not drawn[outside].any(), f"{drawn[outside].sum()} pixels drawn outside the disc"
    # the drawn area equals the predicted one to a fraction of the limb's length in pixels
    band = ~inside & ~outside
    assert abs(int(drawn.sum()) - int((angle < rho).sum())) <= 0.5 * band.sum() + 2
    assert (out.mask_u8 == 0).all() and (out.depth_m == 0).all()  # the Earth is background


def test_the_sun_lights_the_day_side_the_terminator_between(renderer):
    """A GEO Earth lit from the side: the half toward the sun is bright, the other dark (ambient only)."""
    R_K_from_C = renderer._R_K_from_C
    nadir_K = np.array([0.0, 0.0, 1.0])
    sun_K = np.array([1.0, 0.0, 0.0])  # toward image right, square to the line of sight
    view = View(np.array([0.0, -60.0, 0.0]), np.eye(3), R_K_from_C.T @ sun_K, R_K_from_C.T @ nadir_K, 42164e3)
    img = renderer.render(view).gray_u8.astype(float)
    angle, rho, _ = predicted_disc(renderer.K, nadir_K, 42164e3)
    disc = angle < rho - 2.0 / renderer.K[0, 0]
    u = np.arange(RES)[None, :].repeat(RES, 0)
    c = renderer.K[0, 2]
    day, night = disc & (u > c + 4), disc & (u < c - 4)
    assert img[day].mean() > 10 and img[night].mean() < 2, (img[day].mean(), img[night].mean())
    assert img[day].mean() > 10 * max(img[night].mean(), 0.5)
    # Lambert's law across the disc: the day side brightens toward the sub-solar limb
    r_px = renderer.K[0, 0] * math.tan(rho)
    assert img[disc & (u > c + 0.6 * r_px)].mean() > img[disc & (u > c + 4) & (u < c + 0.3 * r_px)].mean()


def test_never_over_the_target_and_mask_depth_unchanged(renderer):
    """With the Earth filling the frame behind the target, the target's pixels (away from its antialiased
    outline), its mask and depth are those of the render without the Earth. (Reflective foil mirrors the
    Earth, as it mirrors the rest of the scene: MuJoCo's reflections are off here, so only occlusion is
    tested.)"""
    import mujoco

    R_K_from_C = renderer._R_K_from_C
    rng = np.random.default_rng(0)
    flag = mujoco.mjtRndFlag.mjRND_REFLECTION
    renderer._scene.flags[flag] = False
    try:
        _target_untouched(renderer, R_K_from_C, rng)
    finally:
        renderer._scene.flags[flag] = True


def _target_untouched(renderer, R_K_from_C, rng):
    for k in range(3):
        q = unit(rng.standard_normal(4))
        from envisat_pose.attitude import quat_to_rotmat

        rho = R_K_from_C.T @ np.array([rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(35, 60)])
        nadir_K = unit([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), 1.0])
        sun_K = unit([0.3, -0.2, -1.0])
        base = View(rho, quat_to_rotmat(q), R_K_from_C.T @ sun_K, R_K_from_C.T @ nadir_K, 7142e3,
                    earth_quat_C=earth.random_rotation_quat(rng), earth_backdrop=False)
        import dataclasses

        with_earth = renderer.render(dataclasses.replace(base, earth_backdrop=True))
        without = renderer.render(base)
        assert np.array_equal(with_earth.mask_u8, without.mask_u8)
        assert np.array_equal(with_earth.depth_m, without.depth_m)
        np.testing.assert_array_equal(with_earth.corners_K_m, without.corners_K_m)
        target = cv2.erode((without.mask_u8 > 0).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        assert target.sum() > 50
        assert np.array_equal(with_earth.gray_u8[target], without.gray_u8[target])
        background = cv2.dilate((without.mask_u8 > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) == 0
        assert with_earth.gray_u8[background].mean() > without.gray_u8[background].mean() + 5  # the Earth is there


def test_out_of_frame_earth_is_not_drawn(renderer):
    """A V-bar view (boresight 90 deg from nadir, nadir toward image down) at 7142 km: the disc (63.3 deg)
    stops 26.7 deg short of the boresight, outside the 30 deg field of view: not drawn. Closed form: the image
    ray nearest the nadir is the bottom row's centre, atan((H - 1 - c) / f) below the boresight, so the disc
    reaches the image when asin(R / r) > 90 deg - that angle (below ~225 km altitude)."""
    R_K_from_C = renderer._R_K_from_C
    nadir_C = np.array([-1.0, 0.0, 0.0])
    assert np.allclose(R_K_from_C @ nadir_C, [0.0, 1.0, 0.0])  # image down
    v = View(np.array([0.0, 50.0, 0.0]), np.eye(3), unit([0.2, -1.0, 0.1]), nadir_C, 7142e3)
    assert not renderer.earth_drawn(v)
    edge = math.atan((RES - 1 - renderer.K[1, 2]) / renderer.K[1, 1])
    for r_m in (6450e3, 6550e3, 6700e3, 6778e3, 7142e3):
        reaches = math.asin(EARTH_RADIUS_M / r_m) > math.pi / 2 - edge
        assert earth.earth_in_frame(R_K_from_C @ nadir_C, r_m, renderer.K, RES) == reaches, r_m
        assert renderer.earth_drawn(View(v.rho_C_m, v.R_C_from_T, v.sun_dir_C, nadir_C, r_m)) == reaches
    assert earth.earth_in_frame(R_K_from_C @ nadir_C, 6450e3, renderer.K, RES)


def test_texture_is_seeded_and_looks_like_the_earth():
    a = earth.earth_texture(0, 512, 0)
    assert a.shape == (256, 512, 3) and a.dtype == np.uint8
    assert np.array_equal(a, earth.earth_texture.__wrapped__(0, 512, 0))  # rebuilt: the same bytes
    assert not np.array_equal(a, earth.earth_texture(1, 512, 0))
    assert not np.array_equal(a, earth.earth_texture(0, 512, 1))
    g = a.mean(axis=-1) / 255.0
    w = np.cos(np.radians(90 - (np.arange(256) + 0.5) * 180 / 256))[:, None] * np.ones((1, 512))  # area weights
    dark = ((g < 0.1) * w).sum() / w.sum()  # open ocean
    bright = ((g > 0.5) * w).sum() / w.sum()  # clouds and ice
    assert 0.2 < dark < 0.75 and 0.15 < bright < 0.7, (dark, bright)
    # seamless at the date line: the first and last columns are neighbours
    assert np.abs(g[:, 0] - g[:, -1]).mean() < 2.5 * np.abs(g[:, 0] - g[:, 1]).mean() + 0.01


def test_cap_mesh_faces_outward_and_maps_like_its_texture():
    m = earth.cap_mesh(2.0, 10.0)
    v, uv, f = m["vertex"], m["texcoord"], m["face"]
    assert np.allclose(np.linalg.norm(v, axis=1), 1.0)
    theta = np.degrees(np.arccos(np.clip(v[:, 0], -1, 1)))
    assert theta.max() == pytest.approx(earth.CAP_HALF_ANGLE_DEG)
    # the texture coordinates are those cap_dirs inverts: texel centre -> direction -> the same vertex
    dirs, _ = earth.cap_dirs(512, 512)
    iu = np.clip((uv[:, 0] * 512).astype(int), 0, 511)
    iv = np.clip((uv[:, 1] * 512).astype(int), 0, 511)
    assert np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", dirs[iv, iu], v), -1, 1))).max() < 0.2
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    normal = np.cross(b - a, c - a)
    assert (np.linalg.norm(normal, axis=1) > 1e-6).all()
    assert (np.einsum("ij,ij->i", normal, a + b + c) > 0).all()


def test_facing_attitude_puts_the_cap_under_the_chaser():
    rng = np.random.default_rng(0)
    for _ in range(50):
        up = unit(rng.standard_normal(3))
        R = earth.facing_attitude(up, rng)
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.linalg.det(R) > 0
        assert math.degrees(math.acos(min(1.0, R[:, 0] @ up))) <= earth.CAP_TILT_MAX_DEG + 1e-9


def test_sphere_mesh_is_closed_and_its_texture_coordinates_are_longitude_latitude():
    m = earth.sphere_mesh(10.0)
    v, uv, f = m["vertex"], m["texcoord"], m["face"]
    assert np.allclose(np.linalg.norm(v, axis=1), 1.0)
    lon = np.degrees(np.arctan2(v[:, 1], v[:, 0]))
    lat = np.degrees(np.arcsin(v[:, 2]))
    ring = np.abs(lat) < 89.9
    np.testing.assert_allclose(uv[ring, 1], (90.0 - lat[ring]) / 180.0, atol=1e-9)
    du = (uv[ring, 0] * 360.0 - 180.0 - lon[ring] + 180.0) % 360.0 - 180.0
    assert np.abs(du).max() < 1e-6
    # every triangle faces outward (counter-clockwise seen from outside) and none is degenerate
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    normal = np.cross(b - a, c - a)
    assert (np.linalg.norm(normal, axis=1) > 1e-6).all()
    assert (np.einsum("ij,ij->i", normal, a + b + c) > 0).all()


def test_random_backdrop_draws_are_seeded_in_the_frame_and_not_eclipsing_the_sun():
    K = np.array([[RES / 2 / math.tan(math.radians(15)), 0, (RES - 1) / 2], [0, RES / 2 / math.tan(math.radians(15)),
                  (RES - 1) / 2], [0, 0, 1.0]])
    for seed in range(20):
        sun = unit(np.random.default_rng(100 + seed).standard_normal(3))
        a = earth.draw_backdrop(np.random.default_rng(seed), (6978e3, 7378e3), K, RES, sun)
        b = earth.draw_backdrop(np.random.default_rng(seed), (6978e3, 7378e3), K, RES, sun)
        assert all(np.array_equal(x, y) for x, y in zip(a, b))
        nadir, r_m, quat, tex = a
        assert 6978e3 <= r_m <= 7378e3 and 0 <= tex < earth.EARTH_TEXTURE_SET_SIZE
        assert earth.earth_in_frame(nadir, r_m, K, RES)
        assert sun @ nadir < math.cos(math.asin(EARTH_RADIUS_M / r_m))


def test_labels_equal_with_and_without_the_earth(tmp_path):
    """The same seed with the Earth in every view and in none: the same labels (but the scene's Earth
    entries), masks and depth; the images differ; twice the same bytes."""
    from envisat_pose.config import from_dict
    from envisat_pose.datagen.factory import run_generate
    from envisat_pose.datagen.generate_config import GenerateConfig
    from envisat_pose.shard_reader import read_shard

    def shard(name, p):
        cfg = from_dict(GenerateConfig, {"num_images": 4, "shard_size": 4, "resolution_px": 96, "seed": 3,
                                         "earth_probability": p})
        man = run_generate(cfg, str(tmp_path / name))
        return list(read_shard(str(tmp_path / name / man["shards"][0]["name"])))

    on, off, again = shard("on", 1.0), shard("off", 0.0), shard("again", 1.0)
    differ = 0
    for (k1, a), (k2, b), (k3, c) in zip(on, off, again):
        assert k1 == k2 == k3 and a == c  # same seed, same bytes
        la, lb = json.loads(a["json"]), json.loads(b["json"])
        assert la["scene"]["earth_backdrop"] and not lb["scene"]["earth_backdrop"]
        for lab in (la, lb):
            lab.pop("scene")
        assert la == lb
        assert a["mask.png"] == b["mask.png"] and a["depth.png"] == b["depth.png"]
        differ += a["png"] != b["png"]
    assert differ >= 2
