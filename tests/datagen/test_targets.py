"""Any spacecraft as the target: a target file the tests write themselves (not a shipped one), its labels against
MuJoCo's rendered site markers, its visibility against MuJoCo's ray cast, its truth against an independent
integration of Euler's equations and two-body orbits; bad target files refused; ENVISAT's datasets unchanged; the
shipped targets' mass properties against their notes.

References independent of the code under test: MuJoCo's renderer (marker pixels) and mj_ray on the test's own file
(no scene built by the code), scipy's solve_ivp (DOP853) with the test's own inertia and orbit, the composite
inertia of the shipped targets recomputed from the dimensions their notes state.
"""

import importlib
import json
import math
import os
import sys

import mujoco
import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from orbit_elements import MU, elements_to_rv  # noqa: E402  (the tests' shared two-body reference)

from envisat_pose.app.cli import main
from envisat_pose.config import from_dict
from envisat_pose.datagen.generate_config import GenerateConfig
from envisat_pose.shard_reader import read_shard

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
# the test's own target: a brick with a fin and a mesh wedge; full inertia with products (not principal axes)
J_TEST = np.array([[2.0, 0.15, -0.1], [0.15, 3.1, 0.05], [-0.1, 0.05, 3.9]])
KEYPOINTS_T_M = {f"c{i}": (sx * 0.6, sy * 0.3, sz * 0.2) for i, (sx, sy, sz) in enumerate(
    (sx, sy, sz) for sx in (1, -1) for sy in (1, -1) for sz in (1, -1))}
KEYPOINTS_T_M.update({"fin_fwd": (0.4, 0.0, 0.8), "fin_aft": (-0.4, 0.0, 0.8)})
# a square plate at each keypoint, parallel to the image plane: it projects as a square centred on the keypoint's
# image, exactly (a cube's or a sphere's outline is not centred: perspective, the sphere's polygon)
MARKER_HALF_M = 0.05


def target_xml(markers: np.ndarray | None = None, keypoints: dict | None = None, inertial: str | None = None,
               extra: str = "", body: str = "target") -> str:
    """The test's target file: geoms (or, given markers = R_K_from_T of a view, only a thin square plate at each
    keypoint, parallel to that view's image plane), its kp_ sites."""
    kps = KEYPOINTS_T_M if keypoints is None else keypoints
    inertial = inertial or '<inertial pos="0 0 0" mass="50" fullinertia="2.0 3.1 3.9 0.15 -0.1 0.05"/>'
    if markers is not None:
        c, s = math.cos(0.37), math.sin(0.37)  # turned in the image plane: no edge along a pixel row or column
        plate = np.concatenate([c * markers[0] + s * markers[1], -s * markers[0] + c * markers[1]])
        axes = " ".join(repr(float(v)) for v in plate)  # in T: two axes in the plane of x_K, y_K
        geoms = "".join(f'<geom name="marker_{n}" type="box" size="{MARKER_HALF_M} {MARKER_HALF_M} 0.0005" '
                        f'pos="{p[0]} {p[1]} {p[2]}" xyaxes="{axes}"/>' for n, p in kps.items())
    else:
        geoms = ('<geom name="brick" type="box" size="0.6 0.3 0.2" material="grey"/>'
                 '<geom name="fin" type="box" pos="0 0 0.5" size="0.4 0.02 0.3" rgba="0.3 0.3 0.8 1"/>'
                 '<geom name="wedge" type="mesh" mesh="wedge" pos="0.6 0.3 0.2" material="grey"/>')
    sites = "".join(f'<site name="kp_{n}" pos="{p[0]} {p[1]} {p[2]}"/>' for n, p in kps.items())
    return (f'<mujoco model="test_brick"><asset><mesh name="wedge" vertex="0 0 0 0.3 0 0 0 0.3 0 0 0 0.3"/>'
            f'<material name="grey" rgba="0.6 0.6 0.6 1" specular="0.3"/>{extra}</asset>'
            f'<worldbody><body name="{body}">{inertial}{geoms}{sites}</body></worldbody></mujoco>')


@pytest.fixture(scope="module")
def target_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("targets")
    plain = folder / "brick.xml"
    plain.write_text(target_xml())
    return str(plain), str(folder)


def test_labels_land_on_the_rendered_site_markers(target_files):
    """A square plate facing the camera at every keypoint site, rendered by MuJoCo at 2048 px (55 px a side): the centroid of each whole marker's mask pixels (pixel centres at integers) is the label's keypoint within 0.05 px; the labels of the file without
    markers are the same numbers (the geoms do not move the keypoints)."""
    from envisat_pose.datagen.labels import make_label
    from envisat_pose.datagen.render import SceneRenderer
    from envisat_pose.datagen.render_view import View
    from envisat_pose.datagen.views import R_K_FROM_C
    from envisat_pose.target import load_target

    plain, folder = target_files
    names = load_target(plain).keypoint_names
    r_plain = SceneRenderer(256, target=plain)
    rng = np.random.default_rng(48)
    checked = 0
    for n_view in range(2):
        R = Rotation.random(random_state=rng).as_matrix()
        view = View(np.array([0.2, 7.0, -0.1]), R, np.array([0.0, -1.0, 0.0]))
        marked = os.path.join(folder, f"brick_markers_{n_view}.xml")
        with open(marked, "w") as fh:
            fh.write(target_xml(markers=R_K_FROM_C @ R))
        r_marked = SceneRenderer(2048, shadows=False, target=marked)
        try:
            out = r_marked.render(view)
            K = r_marked.K
            label = make_label(out.corners_K_m, np.ones(len(names), bool), K, out.R_K_from_T, out.t_K_from_T_m,
                               np.zeros(12), 0.002, {}, 0, {}, names)
            px = np.array(label["keypoints_px"])
            other = r_plain.render(view).corners_K_m
            assert np.allclose(other, out.corners_K_m, atol=1e-9)
            for k, name in enumerate(names):
                value = r_marked.mask_values[f"marker_{name}"]
                rows, cols = np.nonzero(out.mask_u8 == value)
                if len(rows) == 0:
                    continue
                window = out.mask_u8[rows.min() - 2:rows.max() + 3, cols.min() - 2:cols.max() + 3]
                if np.any((window != 0) & (window != value)):
                    continue  # touching another marker: maybe partly hidden, its centroid not the centre
                centroid = np.array([cols.mean(), rows.mean()])
                assert np.abs(centroid - px[k]).max() < 0.05, (name, centroid, px[k])
                checked += 1
        finally:
            r_marked.close()
    r_plain.close()
    assert checked >= 12


RAY_TOL_M = 1e-3  # the keypoints lie on the surface: a hit within 1 mm of one is the keypoint's own surface


def _ray_visible(model, label: dict, points_T_m: np.ndarray) -> np.ndarray:
    """(K,) bool: MuJoCo's ray from the camera to each keypoint, cast in the test's own file (body 'target' at
    the origin: rays in T), hits nothing nearer than the keypoint less RAY_TOL_M, and the keypoint is in front."""
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    R, t = np.array(label["R_cam_from_target"]), np.array(label["t_cam_from_target_m"])
    cam_T = -R.T @ t
    out = np.zeros(len(points_T_m), dtype=bool)
    geomid = np.zeros(1, dtype=np.int32)
    for k, p in enumerate(points_T_m):
        dist = np.linalg.norm(p - cam_T)
        z = (R @ p + t)[2]
        hit = mujoco.mj_ray(model, data, cam_T, (p - cam_T) / dist, None, 1, -1, geomid)
        out[k] = (hit < 0 or hit >= dist - RAY_TOL_M) and z > 0
    return out


def test_visibility_agrees_with_mujocos_ray_cast(target_files, tmp_path):
    """Random views of the test's target (the factory, 256 px, 3-6 m: hidden corners, the fin's rim, the wedge):
    the labels' visibility of every keypoint in the frame agrees with MuJoCo's ray cast through the test's own file
    (mj_ray over the whole model, not the code's per-geom casts) for at least 99.5 % of them."""
    from envisat_pose.datagen.factory import run_generate
    from envisat_pose.target import load_target

    plain, _ = target_files
    cfg = from_dict(GenerateConfig, {"target": plain, "num_images": 24, "shard_size": 24, "resolution_px": 256,
                                     "seed": 7, "earth_probability": 0.0,
                                     "random": {"range_min_m": 3.0, "range_max_m": 6.0, "keepout_margin_m": 0.5}})
    manifest = run_generate(cfg, str(tmp_path / "d"))
    model = mujoco.MjModel.from_xml_path(plain)
    target = load_target(plain)
    points = np.array(list(KEYPOINTS_T_M.values()))
    agree = total = hidden = 0
    for _, members in read_shard(str(tmp_path / "d" / manifest["shards"][0]["name"])):
        label = json.loads(members["json"])
        assert label["keypoint_names"] == list(KEYPOINTS_T_M) and "corners_px" not in label
        frame = np.array(label["in_frame"])
        ray = _ray_visible(model, label, points)
        agree += int(np.sum(ray[frame] == np.array(label["visible"])[frame]))
        total += int(frame.sum())
        hidden += int(np.sum(~ray[frame]))
    assert total >= 200 and agree / total >= 0.995 and hidden >= 20, (agree, total, hidden)
    assert manifest["target"]["sha256"] == target.sha256 and manifest["mask_values"] == {
        "background": 0, "brick": 1, "fin": 2, "wedge": 3}


# --- truth against Euler's equations and two-body orbits -----------------------------------------------------



def _two_body(r0, v0, t):
    sol = solve_ivp(lambda _, y: np.concatenate([y[3:], -MU * y[:3] / np.linalg.norm(y[:3]) ** 3]), (0, t[-1]),
                    np.concatenate([r0, v0]), method="DOP853", t_eval=t, rtol=1e-13, atol=1e-7)
    return sol.y[:3].T, sol.y[3:].T


def _lvlh(r, v):
    x = r / np.linalg.norm(r, axis=-1, keepdims=True)
    h = np.cross(r, v)
    z = h / np.linalg.norm(h, axis=-1, keepdims=True)
    return np.stack([x, np.cross(z, x), z], axis=-1), h / np.sum(r * r, axis=-1, keepdims=True)


def _gamma(p):
    """Gamma(p) (T from C) from the reference sheet's formula."""
    pp = p @ p
    S = np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])
    return np.eye(3) - 4 * (1 - pp) / (1 + pp) ** 2 * S + 8 / (1 + pp) ** 2 * S @ S


def _euler(t, y):
    """Torque-free rigid body: quaternion (x, y, z, w; N from T) and w_T, Euler's equations with J_TEST."""
    q, w = y[:4], y[4:]
    x, yy, z, s = q
    dq = 0.5 * np.array([s * w[0] + yy * w[2] - z * w[1], s * w[1] + z * w[0] - x * w[2],
                         s * w[2] + x * w[1] - yy * w[0], -(x * w[0] + yy * w[1] + z * w[2])])
    return np.concatenate([dq, np.linalg.solve(J_TEST, -np.cross(w, J_TEST @ w))])


def test_truth_of_the_tests_target_follows_eulers_equations_and_the_orbits(target_files):
    """30 minutes of the MuJoCo truth of the test's target (full inertia with products, so MuJoCo's principal axes
    are not the file's): attitude within 1e-6 rad and relative rates within 1e-9 rad/s of Euler's equations
    integrated by scipy with J_TEST, the relative position within 1e-5 m of two inertial two-body orbits."""
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate_truth

    plain, _ = target_files
    cfg = scenario_config(duration_s=1800.0, dt_s=10.0, seed=4, target={"file": plain, "spin_period_s": 60.0},
                          relative={"rho0_C_m": [0.5, 8.0, -0.3], "rhodot0_C_m_s": [0.001, 0.0, -0.002]})
    traj = simulate_truth(cfg)
    o = cfg.orbit
    t = traj.t_s
    r_c0, v_c0 = elements_to_rv(o.a_m, o.e, o.i_deg, o.raan_deg, o.argp_deg, o.nu0_deg)
    r_c, v_c = _two_body(r_c0, v_c0, t)
    R_N_C, w_c_N = _lvlh(r_c, v_c)
    x0 = traj.x[0]
    r_t0 = r_c0 + R_N_C[0] @ x0[:3]
    v_t0 = v_c0 + R_N_C[0] @ (x0[3:6] + np.cross(R_N_C[0].T @ w_c_N[0], x0[:3]))
    r_t, _ = _two_body(r_t0, v_t0, t)
    rho_ref = np.einsum("nji,nj->ni", R_N_C, r_t - r_c)
    assert np.abs(rho_ref - traj.x[:, :3]).max() < 1e-5
    G0 = _gamma(x0[6:9])
    w_t0 = x0[9:12] + G0 @ (R_N_C[0].T @ w_c_N[0])
    q0 = Rotation.from_matrix(R_N_C[0] @ G0.T).as_quat()
    sol = solve_ivp(_euler, (0, t[-1]), np.concatenate([q0, w_t0]), method="DOP853", t_eval=t, rtol=1e-13,
                    atol=1e-14)
    R_N_T = Rotation.from_quat(sol.y[:4].T).as_matrix()
    R_C_T_ref = np.einsum("nji,njk->nik", R_N_C, R_N_T)
    R_C_T = np.array([_gamma(p).T for p in traj.x[:, 6:9]])
    err = np.arccos(np.clip((np.trace(R_C_T_ref @ np.swapaxes(R_C_T, 1, 2), axis1=1, axis2=2) - 1) / 2, -1, 1))
    assert err.max() < 1e-6
    w_r_ref = sol.y[4:].T - np.einsum("nij,nj->ni", np.swapaxes(R_C_T_ref, 1, 2),
                                      np.einsum("nji,nj->ni", R_N_C, w_c_N))
    assert np.abs(w_r_ref - traj.x[:, 9:12]).max() < 1e-9
    assert traj.corners_px.shape == (len(t), len(KEYPOINTS_T_M), 2)


# --- bad target files -----------------------------------------------------------------------------------------

FAR = dict(KEYPOINTS_T_M, far=(0.6, -0.3, 0.6))  # 0.344 m from the fin, its nearest geom
BAD = {
    "no body target": (target_xml(body="satellite"), "a body named 'target'"),
    "three keypoints": (target_xml(keypoints=dict(list(KEYPOINTS_T_M.items())[:3])), "at least 4 keypoint sites"),
    "inertia not positive definite": (target_xml(inertial='<inertial pos="0 0 0" mass="5" '
                                                          'fullinertia="1 1 1 2 0 0"/>'), "positive definite"),
    "triangle inequality": (target_xml(inertial='<inertial pos="0 0 0" mass="5" diaginertia="1 1 3"/>'),
                            "triangle inequality"),
    "zero mass": (target_xml(inertial='<inertial pos="0 0 0" mass="0" diaginertia="1 1 1"/>'), "a positive mass"),
    "mesh that does not load": (target_xml(extra='<mesh name="hull" file="no_such_hull.stl"/>'), "MuJoCo compiles"),
    "keypoint off the target": (target_xml(keypoints=FAR), "site 'kp_far' is 0.344 m from the nearest surface of the geoms"),
    "no geom drawn": (target_xml().replace('<geom name=', '<geom group="3" name='), "groups [3]"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_a_bad_target_file_is_refused_in_one_line_writing_nothing(case, tmp_path, capsys):
    text, expected = BAD[case]
    path = tmp_path / "bad.xml"
    path.write_text(text)
    out = tmp_path / "out"
    verbs = [["generate", "--num-images", "2", "--out", str(out)], ["simulate", "--out", str(out / "run.npz")]]
    for verb in verbs if case in ("zero mass", "mesh that does not load") else verbs[:1]:
        capsys.readouterr()
        assert main([verb[0], "--target", str(path), *verb[1:]]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "target" in err and expected in err, err
        assert not out.exists()


# --- ENVISAT unchanged ----------------------------------------------------------------------------------------

# Two small ENVISAT datasets (128 px, seed 48: 6 random views in shards of 3, 4 sequence frames in shards of 2) as the
# code before any target work wrote them, decoded: tests/data/envisat_shards_reference.npz, written by
# tests/data/make_shard_reference.py (its docstring tells the history). Compared within the cross-machine
# tolerances of tests/data/compare.py: rendered images and printed floats are not the same bytes on every machine.
DATA = os.path.join(ROOT, "tests", "data")
LABEL_ABS = 1e-4  # the coarsest rounding a label is written with (corners_px: 4 decimals), whose last digit a
LABEL_REL = 1e-9  # last-bit difference upstream can flip; any other number to 1e-9 relative


def _load_reference_module(name):
    sys.path.insert(0, DATA)
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(DATA)


def assert_labels_close(now, before, where):
    """Two labels (parsed JSON) the same: keys, strings, integers and flags equal; numbers within LABEL_ABS or
    LABEL_REL."""
    if isinstance(before, dict):
        assert isinstance(now, dict) and sorted(now) == sorted(before), f"{where}: keys {sorted(now)}"
        for k in before:
            assert_labels_close(now[k], before[k], f"{where}.{k}")
    elif isinstance(before, list):
        assert isinstance(now, list) and len(now) == len(before), f"{where}: length"
        for i, (a, b) in enumerate(zip(now, before)):
            assert_labels_close(a, b, f"{where}[{i}]")
    elif isinstance(before, float):
        assert isinstance(now, float | int) and math.isclose(now, before, rel_tol=LABEL_REL, abs_tol=LABEL_ABS), \
            f"{where}: {now!r} against {before!r}"
    else:
        assert type(now) is type(before) and now == before, f"{where}: {now!r} against {before!r}"


def assert_dataset_like_reference(now, before):
    compare = _load_reference_module("compare")
    assert sorted(now) == sorted(before)
    for name in sorted(before):
        a, b = now[name], before[name]
        if name.endswith("/json"):
            assert_labels_close(json.loads(str(a)), json.loads(str(b)), name)
        elif name.endswith("/depth.png"):
            compare.assert_render_close(a, b, name, tol=1)  # one 2 mm step
        elif name.endswith("/mask.png"):
            compare.assert_render_close(a, b, name)
        else:
            compare.assert_noisy_image_close(a, b, name)


@pytest.mark.parametrize("mode", ["random", "sequence"])
def test_envisat_datasets_are_those_of_before_the_target_work(mode, tmp_path):
    """The samples are those of before (images, depth, masks and labels within the cross-machine tolerances); the
    manifest adds only the target (its record and the config's `target` field), ENVISAT's corners keep their names
    A-H and the labels their corners_px."""
    from envisat_pose.datagen.render_view import MASK_VALUES

    maker = _load_reference_module("make_shard_reference")
    manifest = maker.generate(mode, str(tmp_path / mode))
    now = maker.decode(str(tmp_path / mode), manifest, mode)
    with np.load(os.path.join(DATA, "envisat_shards_reference.npz"), allow_pickle=False) as z:
        before = {k: z[k] for k in z.files if k.startswith(mode + "/")}
    assert_dataset_like_reference(now, before)
    assert manifest["config"]["target"] == "models/envisat.xml"
    assert manifest["target"]["keypoint_names"] == list("ABCDEFGH") and manifest["target"]["name"] == "envisat"
    assert manifest["mask_values"] == {"background": 0, **MASK_VALUES}
    label = json.loads(next(iter(read_shard(str(tmp_path / mode / manifest["shards"][0]["name"]))))[1]["json"])
    assert "corners_px" in label and "keypoint_names" not in label


def test_the_dataset_comparison_sees_a_small_change():
    """The comparison above fails for an image moved by one pixel, a corner moved by 0.01 px, a visibility flag
    flipped; it passes for the noise redrawn whole (the worst a machine difference can do)."""
    with np.load(os.path.join(DATA, "envisat_shards_reference.npz"), allow_pickle=False) as z:
        before = {k: z[k] for k in z.files if k.startswith("sequence/")}
    image = "sequence/000000001/png"
    moved = dict(before, **{image: np.roll(before[image], 1, axis=1)})
    with pytest.raises(AssertionError, match="DN"):
        assert_dataset_like_reference(moved, before)
    label = json.loads(str(before["sequence/000000001/json"]))
    label["corners_px"][3][0] += 0.01
    with pytest.raises(AssertionError, match="corners_px"):
        assert_dataset_like_reference(dict(before, **{"sequence/000000001/json": np.array(json.dumps(label))}), before)
    label = json.loads(str(before["sequence/000000001/json"]))
    label["visible"][0] = not label["visible"][0]
    with pytest.raises(AssertionError, match="visible"):
        assert_dataset_like_reference(dict(before, **{"sequence/000000001/json": np.array(json.dumps(label))}), before)


# --- the shipped targets --------------------------------------------------------------------------------------

def _box_inertia(m, a, b, c):
    return np.diag([m / 12 * (b * b + c * c), m / 12 * (a * a + c * c), m / 12 * (a * a + b * b)])


def _shift(m, d):
    d = np.asarray(d, dtype=float)
    return m * (d @ d * np.eye(3) - np.outer(d, d))


def _cubesat_inertia():
    """The note of models/cubesat_3u.xml: a 3.6 kg 0.1 x 0.1 x 0.3405 m body, two 0.2 kg 2 mm x 0.2 x 0.3 m wings
    centred 0.15 m off the axis along +-y."""
    return _box_inertia(3.6, 0.1, 0.1, 0.3405) + sum(_box_inertia(0.2, 0.002, 0.2, 0.3) + _shift(0.2, (0, s * 0.15, 0))
                                                      for s in (1, -1))


def _upper_stage_inertia():
    """The note of models/upper_stage.xml: a thin-walled 8300 kg tank (r 1.95 m, 9 m) and a solid 600 kg engine
    (r 0.7 m, 1.5 m) aft of it, about their common CoM."""
    c = 600 * 5.25 / 8900  # the CoM forward of the tank's centre
    shell = np.diag([8300 * 1.95**2, 8300 * (1.95**2 / 2 + 81 / 12), 8300 * (1.95**2 / 2 + 81 / 12)])
    engine = np.diag([600 * 0.49 / 2, 600 * (3 * 0.49 + 2.25) / 12, 600 * (3 * 0.49 + 2.25) / 12])
    return shell + _shift(8300, (c, 0, 0)) + engine + _shift(600, (c - 5.25, 0, 0))


@pytest.mark.parametrize("name, mass_kg, inertia, range_m", [
    ("cubesat_3u", 4.0, _cubesat_inertia, (1.5, 3.0)), ("upper_stage", 8900.0, _upper_stage_inertia, (25.0, 40.0))])
def test_a_shipped_target_matches_its_note_and_generates(name, mass_kg, inertia, range_m, tmp_path, capsys):
    """Mass and inertia of the file as its note computes them (within 1e-4 relative); `envisat generate
    --target models/<name>.xml` writes labels with its 12 named keypoints."""
    from envisat_pose.target import load_target

    target = load_target(f"models/{name}.xml")
    assert target.mass_kg == mass_kg
    assert np.allclose(target.inertia_T_kg_m2, inertia(), rtol=1e-4, atol=1e-6)
    config = tmp_path / "c.toml"
    config.write_text(f"earth_probability = 0.0\n[random]\nrange_min_m = {range_m[0]}\nrange_max_m = {range_m[1]}\n"
                      "keepout_margin_m = 0.5\n")
    out = tmp_path / "d"
    assert main(["generate", "--target", f"models/{name}.xml", "--config", str(config), "--num-images", "2",
                 "--resolution", "96", "--seed", "3", "--out", str(out), "--quiet"]) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["target"]["name"] == name and len(manifest["target"]["keypoint_names"]) == 12
    for _, members in read_shard(str(out / manifest["shards"][0]["name"])):
        label = json.loads(members["json"])
        assert len(label["keypoints_px"]) == len(label["visible"]) == len(label["in_frame"]) == 12
        assert label["keypoint_names"] == list(target.keypoint_names) and any(label["visible"])


def test_the_detector_verbs_refuse_another_target_in_one_line(target_files, tmp_path, capsys):
    """detect, train, track, adapt, calibrate and evaluate on a dataset of the test's target, and run with it as its
    image target: exit 2, one line naming the field and ENVISAT, nothing written. (`estimate --truth` takes any
    target's truth: tests/app/test_estimate_cli.py; `track` and `run` take it with --target and its own keypoint
    detector: tests/app/test_track_target.py, test_run_target.py; without those, the dataset or the missing
    weights are named.)"""
    plain, _ = target_files
    data = tmp_path / "seq"
    assert main(["generate", "--target", plain, "--mode", "sequence", "--num-images", "2", "--resolution", "64",
                 "--out", str(data), "--quiet"]) == 0
    run_config = tmp_path / "run.toml"
    run_config.write_text(f'[image]\ntarget = "{plain}"\n')
    out = tmp_path / "out"
    for argv, field in [(["detect", "--data", str(data), "--out", str(out / "det.npz")], "data"),
                        (["train", "--data", str(data), "--out", str(out)], "data"),
                        (["track", "--images", str(data), "--out", str(out)], "--images"),
                        (["adapt", "--images", str(data), "--out", str(out)], "--images"),
                        (["run", "--config", str(run_config), "--duration-s", "5", "--out", str(out)], "weights"),
                        (["calibrate", "--data", str(data), "--out", str(out / "w.safetensors")], "data"),
                        (["evaluate", "--data", str(data), "--json", str(out / "eval.json")], "data")]:
        capsys.readouterr()
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and field in err and "ENVISAT" in err and f"envisat {argv[0]}" in err, err
        assert not out.exists()


def test_every_export_format_carries_the_targets_keypoints_and_name(target_files, tmp_path):
    """A dataset of the test's target exported as SPEED+, COCO, BOP and YOLO-pose: each names the target and its
    K = 10 keypoints (in their file order) and writes K per image; COCO's skeleton is the target's (1-based)."""
    from envisat_pose.datagen.factory import run_generate
    from envisat_pose.pipelines.datasets.export import ExportConfig, export_dataset
    from envisat_pose.target import load_target

    plain, _ = target_files
    src = str(tmp_path / "d")
    run_generate(from_dict(GenerateConfig, {"target": plain, "num_images": 3, "shard_size": 3, "resolution_px": 96,
                                            "seed": 9, "random": {"range_min_m": 3.0, "range_max_m": 5.0,
                                                                  "keepout_margin_m": 0.5}}), src)
    names = list(KEYPOINTS_T_M)
    for fmt in ("speedplus", "coco", "bop", "yolo-pose"):
        out = tmp_path / fmt
        export_dataset(src, str(out), ExportConfig(fmt, val_fraction=0.0), progress=False)
        record = json.loads((out / "export.json").read_text())
        assert record["target"]["name"] == "test_brick" and record["keypoint_names"] == names, fmt
        assert record["target"]["sha256"] == load_target(plain).sha256, fmt
    coco = json.loads((tmp_path / "coco" / "annotations" / "keypoints_train.json").read_text())
    skeleton = [[i + 1, j + 1] for i, j in load_target(plain).skeleton]
    assert coco["categories"][0]["keypoints"] == names and coco["categories"][0]["skeleton"] == skeleton
    assert len(skeleton) >= 12  # the brick's 12 edges at least
    assert all(len(a["keypoints"]) == 3 * len(names) for a in coco["annotations"])
    rows = [line.split() for p in (tmp_path / "yolo-pose" / "labels" / "train").iterdir() for line in p.read_text().splitlines()]
    assert rows and all(len(r) == 5 + 3 * len(names) for r in rows)
    assert f"kpt_shape: [{len(names)}, 3]" in (tmp_path / "yolo-pose" / "data.yaml").read_text()
    points = json.loads((tmp_path / "bop" / "models" / "keypoints_3d.json").read_text())["1"]
    assert points["names"] == names and np.allclose(np.array(points["points_mm"]) / 1000.0,
                                                    np.array(list(KEYPOINTS_T_M.values())))
