"""The array cue (perception/arraycue.py) on MuJoCo renders: the end of the body the image shows the array at,
right under the true pose, reversed under its twins by the half-turns about y and z, silent where it cannot see."""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import numpy as np
import pytest

from envisat_pose.attitude import quat_to_rotmat
from envisat_pose.geometry import load_array_outline, load_geometry, model_path
from envisat_pose.perception.arraycue import array_end
from envisat_pose.perception.box_symmetry import symmetry_permutations

RES = 512


def test_the_outline_is_the_mjcf_array_as_mujoco_compiles_it():
    import mujoco

    m = mujoco.MjModel.from_xml_path(model_path())
    gid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "array")
    pos, size = m.geom_pos[gid], m.geom_size[gid]
    assert np.allclose(m.geom_quat[gid], [1, 0, 0, 0])  # unrotated in its body, as the outline assumes
    out = load_array_outline()
    long_axes = np.argsort(size)[1:]
    for ax in long_axes:
        assert out[:, ax].min() == pytest.approx(pos[ax] - size[ax]) and out[:, ax].max() == pytest.approx(pos[ax] + size[ax])
    thin = int(np.argmin(size))
    assert np.allclose(out[:, thin], pos[thin])
    assert out[:, 0].max() < -load_geometry().half_sizes_m[0]  # beyond the body's -x end


@pytest.fixture(scope="module")
def renders():
    """Lit views at 30-45 m near the boresight (random attitude and sun in front of the camera's hemisphere), the
    MJCF's own materials, no Earth: (image, K, R_K_from_T, t_K_from_T_m) each."""
    from envisat_pose.datagen.render import SceneRenderer
    from envisat_pose.datagen.render_view import View

    rng = np.random.default_rng(11)
    r = SceneRenderer(RES)
    out = []
    try:
        for _ in range(16):
            q = rng.standard_normal(4)
            rho = rng.uniform(30.0, 45.0) * np.array([0.0, 1.0, 0.0]) + rng.normal(0.0, 0.5, 3)
            sun = np.array([0.0, -1.0, 0.0]) + rng.normal(0.0, 0.5, 3)  # from behind the camera: lit faces
            res = r.render(View(rho, quat_to_rotmat(q / np.linalg.norm(q)), sun / np.linalg.norm(sun)), labels=False)
            out.append((res.gray_u8, r.K, res.R_K_from_T, res.t_K_from_T_m))
    finally:
        r.close()
    return out


def twin(R, t, name):
    """The pose of the same image under the box's half-turn `name` (the corners' names permuted)."""
    _, S, d = symmetry_permutations(load_geometry())[name]
    return R @ S, t + R @ d


def test_true_pose_reads_its_end_and_the_y_z_twins_the_other(renders):
    corners = load_geometry().corners_T_m
    spoke = 0
    for img, K, R, t in renders:
        cue, det = array_end(img, K, R, t, corners)
        assert cue >= 0, det  # never the wrong end
        spoke += cue == 1
        for name in ("y", "z"):
            assert array_end(img, K, *twin(R, t, name), corners)[0] == -cue
        assert array_end(img, K, *twin(R, t, "x"), corners)[0] == cue  # the x half-turn keeps the array's end
    assert spoke >= 6, spoke  # it does read lit views


def test_a_lit_background_or_an_empty_frame_says_nothing(renders):
    corners = load_geometry().corners_T_m
    img, K, R, t = next(r for r in renders if array_end(r[0], r[1], r[2], r[3], corners)[0] == 1)
    lit = img.copy()
    lit[: RES // 3] = np.maximum(lit[: RES // 3], 90)  # the Earth over a third of the frame
    assert array_end(lit, K, R, t, corners)[0] == 0
    assert array_end(np.zeros_like(img), K, R, t, corners)[0] == 0  # nothing lit: no reading
    far = t + np.array([0.0, 0.0, 400.0])  # the target a few pixels wide: regions too small to read
    assert array_end(img, K, R, far, corners)[0] == 0


def test_the_sky_level_from_the_histogram_is_numpys_percentile_and_medians():
    """sky_level (the cue's background statistics from a grey-level histogram) against numpy on the sample itself:
    the median of bg[bg <= np.percentile(bg, 25)] and the median absolute deviation about it, equal on skies of
    every kind (Poisson noise, uniform, long-tailed; odd and even counts)."""
    from envisat_pose.perception.arraycue import sky_level

    rng = np.random.default_rng(7)
    for trial in range(600):
        n = int(rng.integers(100, 3000))
        kind = trial % 3
        if kind == 0:
            bg = rng.poisson(rng.uniform(0.0, 20.0), n)
        elif kind == 1:
            bg = rng.integers(0, 256, n)
        else:
            bg = np.minimum(rng.geometric(rng.uniform(0.05, 0.9), n) - 1, 255)
        bg = bg.astype(np.uint8)
        b = bg.astype(np.float32)
        dark = b[b <= np.percentile(b, 25)]
        floor = float(np.median(dark))
        assert sky_level(np.bincount(bg, minlength=256)) == (floor, float(np.median(np.abs(dark - floor))))
