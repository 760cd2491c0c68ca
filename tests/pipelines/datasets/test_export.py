"""`envisat dataset export`: each format read back by code written here from that format's published conventions
(SPNv2's projection for SPEED+, pycocotools for COCO, the BOP toolkit's pose and box rules, Ultralytics's row
layout), never through the exporter's helpers; and the export's safety: interrupted, damaged, existing --out."""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import hashlib
import json
import shutil

import numpy as np
import pytest

from envisat_pose.app.cli import main as envisat_main
from envisat_pose.config import InputError, from_dict
from envisat_pose.datagen.dataset import iter_samples
from envisat_pose.datagen.export_formats import bop_model_info, vertex_normals
from envisat_pose.datagen.factory import run_generate
from envisat_pose.datagen.generate_config import GenerateConfig
from envisat_pose.geometry import CORNER_NAMES, EDGES, load_geometry
from envisat_pose.pipelines.datasets.export import ExportConfig, export_dataset
from envisat_pose.provenance import dataset_ref, find_absolute_paths

FORMATS = ("speedplus", "coco", "bop", "yolo-pose")


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    """The floors' two cases: 1024 px random views (appendages, Earth, sensor model) and a 512 px sequence."""
    root = tmp_path_factory.mktemp("export")
    rand = str(root / "rand")
    run_generate(from_dict(GenerateConfig, {"num_images": 5, "shard_size": 2, "resolution_px": 1024, "seed": 21,
                                            "earth_probability": 0.5}), rand, workers=2)
    seq = str(root / "seq")
    run_generate(from_dict(GenerateConfig, {"mode": "sequence", "num_images": 4, "shard_size": 3,
                                            "resolution_px": 512, "seed": 4}), seq, workers=2)
    return {"rand": rand, "seq": seq}


@pytest.fixture(scope="module")
def exports(datasets, tmp_path_factory):
    root = tmp_path_factory.mktemp("exported")
    out = {}
    for name, src in datasets.items():
        for fmt in FORMATS:
            vf = 0.25 if fmt in ("coco", "yolo-pose") else None  # a sequence's split: its last frames
            out[name, fmt] = export_dataset(src, str(root / f"{name}-{fmt}"), ExportConfig(fmt, val_fraction=vf),
                                            workers=1, progress=False).out_dir  # inline: no pool to start
    return out


def labels_of(src):
    """[(label, png bytes, mask)] in sample order, read with the factory's reader."""
    from envisat_pose.datagen.shards import decode_png

    return [(lab, m["png"], decode_png(m["mask.png"])) for _, lab, m in iter_samples(src)]


# --- SPEED+: SPNv2's own projection ------------------------------------------------------------------------------

def spnv2_quat2dcm(q):
    """SPNv2's quat2dcm (scalar first; the DCM whose transpose takes body to camera)."""
    q = np.asarray(q, float) / np.linalg.norm(q)
    q0, q1, q2, q3 = q
    return np.array([[2 * q0**2 - 1 + 2 * q1**2, 2 * q1 * q2 + 2 * q0 * q3, 2 * q1 * q3 - 2 * q0 * q2],
                     [2 * q1 * q2 - 2 * q0 * q3, 2 * q0**2 - 1 + 2 * q2**2, 2 * q2 * q3 + 2 * q0 * q1],
                     [2 * q1 * q3 + 2 * q0 * q2, 2 * q2 * q3 - 2 * q0 * q1, 2 * q0**2 - 1 + 2 * q3**2]])


def spnv2_project(q, r, camera, points_3xn):
    """SPNv2's project_keypoints: [R^T(q) | r] on homogeneous points, OpenCV distortion, the camera matrix."""
    pose = np.hstack([spnv2_quat2dcm(q).T, np.asarray(r, float)[:, None]])
    xyz = pose @ np.vstack([points_3xn, np.ones((1, points_3xn.shape[1]))])
    x0, y0 = xyz[0] / xyz[2], xyz[1] / xyz[2]
    d = np.asarray(camera["distCoeffs"], float)
    r2 = x0 * x0 + y0 * y0
    c = 1 + d[0] * r2 + d[1] * r2 * r2 + d[4] * r2**3
    x = x0 * c + d[2] * 2 * x0 * y0 + d[3] * (r2 + 2 * x0 * x0)
    y = y0 * c + d[2] * (r2 + 2 * y0 * y0) + d[3] * 2 * x0 * y0
    K = np.asarray(camera["cameraMatrix"], float)
    return np.stack([K[0, 0] * x + K[0, 2], K[1, 1] * y + K[1, 2]], axis=1)


def speedplus_errors_px(folder, sequence=None):
    """The largest reprojection error of every entry against the factory's labels, and the image names."""
    from scipy.io import loadmat

    with open(os.path.join(folder, "camera.json")) as fh:
        camera = json.load(fh)
    points = loadmat(os.path.join(folder, "models", "keypoints.mat"))["tango3Dpoints"]
    if sequence:
        files = [os.path.join(folder, sequence, f"{sequence}.json")]
        images = os.path.join(folder, sequence, "synthetic", "images")
    else:
        files = [os.path.join(folder, "synthetic", n) for n in ("train.json", "validation.json")]
        images = os.path.join(folder, "synthetic", "images")
    entries = [e for f in files for e in json.load(open(f))]
    return camera, points, entries, images


@pytest.mark.parametrize("case", ["rand", "seq"])
def test_speedplus_reprojects_onto_labels(datasets, exports, case):
    folder = exports[case, "speedplus"]
    seq = "seq" if case == "seq" else None
    camera, points, entries, images = speedplus_errors_px(folder, seq)
    assert points.shape == (3, 8)
    labels = labels_of(datasets[case])
    assert len(entries) == len(labels)
    by_name = {e["filename"]: e for e in entries}
    names = sorted(by_name)
    if seq:
        assert [e["filename"] for e in entries] == names  # frames in time order
        meta = json.load(open(os.path.join(folder, seq, "metadata.json")))
        assert meta["t_s"] == [lab["scene"]["t_s"] for lab, _, _ in labels]
    worst = 0.0
    masks = os.path.join(os.path.dirname(images), "masks")  # SPNv2: <domain>/masks/<filename, jpg -> png>
    assert len(os.listdir(masks)) == len(os.listdir(images)) == len(labels)
    for name, (lab, png, fmask) in zip(names, labels):
        e = by_name[name]
        uv = spnv2_project(e["q_vbs2tango_true"], e["r_Vo2To_vbs_true"], camera, points)
        worst = max(worst, np.abs(uv - np.asarray(lab["corners_px"])).max())
        with open(os.path.join(images, name), "rb") as fh:  # the shard's bytes, unchanged
            assert hashlib.sha256(fh.read()).hexdigest() == hashlib.sha256(png).hexdigest()
        mask = _read_gray(os.path.join(masks, name.replace("jpg", "png")))
        assert mask.shape == fmask.shape and set(np.unique(mask)) <= {0, 255}
        assert np.array_equal(mask > 128, fmask > 0)  # SPNv2's threshold
    assert worst < 1e-3
    n = labels[0][2].shape[0]
    K = np.asarray(camera["cameraMatrix"])
    assert camera["Nu"] == camera["Nv"] == n and K[0, 2] == K[1, 2] == (n - 1) / 2
    assert camera["fx"] == pytest.approx(K[0, 0] * camera["ppx"]) and len(camera["distCoeffs"]) == 5
    assert camera["horizontalFOV"] == pytest.approx(30.0, abs=1e-6)  # the MJCF's fovy, a square image


@pytest.mark.parametrize("defect", ["principal point + 0.5 px", "rotation transposed", "quaternion scalar last"])
def test_speedplus_check_fails_on_a_wrong_convention(datasets, exports, defect):
    """The reader above is able to fail: each convention error an exporter could make moves the reprojection."""
    camera, points, entries, _ = speedplus_errors_px(exports["rand", "speedplus"])
    labels = labels_of(datasets["rand"])
    entries = sorted(entries, key=lambda e: e["filename"])
    worst = 0.0
    for e, (lab, _, _) in zip(entries, labels):
        cam, q = json.loads(json.dumps(camera)), np.asarray(e["q_vbs2tango_true"])
        if defect.startswith("principal"):
            cam["cameraMatrix"][0][2] += 0.5
        elif defect.startswith("rotation"):
            q = q * [1, -1, -1, -1]
        else:
            q = np.roll(q, -1)
        uv = spnv2_project(q, e["r_Vo2To_vbs_true"], cam, points)
        worst = max(worst, np.abs(uv - np.asarray(lab["corners_px"])).max())
    assert worst > 0.4


# --- BOP: the toolkit's pose and box conventions -------------------------------------------------------------------

def bop_frames(folder, defect=None):
    """(corners projected with the BOP pose and cam_K, mask_visib, gt_info, scene_camera) of every image, read
    as the BOP toolkit reads them (cam_R_m2c row-major, mm); `defect` plants a convention error."""
    kp_mm = load_geometry().corners_T_m * 1000.0  # the MJCF's sites, the one source of the geometry
    got = []
    for scene in sorted(os.listdir(os.path.join(folder, "train_pbr"))):
        base = os.path.join(folder, "train_pbr", scene)
        gt = json.load(open(os.path.join(base, "scene_gt.json")))
        cams = json.load(open(os.path.join(base, "scene_camera.json")))
        info = json.load(open(os.path.join(base, "scene_gt_info.json")))
        for im in sorted(gt, key=int):
            R = np.asarray(gt[im][0]["cam_R_m2c"], float).reshape(3, 3)
            t = np.asarray(gt[im][0]["cam_t_m2c"], float)
            K = np.asarray(cams[im]["cam_K"], float).reshape(3, 3)
            if defect == "principal point + 0.5 px":
                K[0, 2] += 0.5
            elif defect == "rotation transposed":
                R = R.T
            elif defect == "translation in metres":
                t = t / 1000.0
            p = (kp_mm @ R.T + t) @ K.T
            mask = _read_gray(os.path.join(base, "mask_visib", f"{int(im):06d}_000000.png"))
            full = _read_gray(os.path.join(base, "mask", f"{int(im):06d}_000000.png"))
            assert np.array_equal(full, mask)  # amodal = visible: one object, nothing occludes it
            got.append((p[:, :2] / p[:, 2:], mask, info[im][0], cams[im]))
    return got


@pytest.mark.parametrize("defect", ["principal point + 0.5 px", "rotation transposed", "translation in metres"])
def test_bop_check_fails_on_a_wrong_convention(datasets, exports, defect):
    labels = labels_of(datasets["rand"])
    got = bop_frames(exports["rand", "bop"], defect)
    worst = max(np.abs(uv - np.asarray(lab["corners_px"])).max() for (uv, *_), (lab, _, _) in zip(got, labels))
    assert worst > 0.4


def test_bop_pose_masks_and_model(datasets, exports):
    for case in ("rand", "seq"):
        labels = labels_of(datasets[case])
        got = bop_frames(exports[case, "bop"])
        assert len(got) == len(labels)
        rgb = sorted(os.path.join(root, f) for root, _, files in os.walk(os.path.join(exports[case, "bop"],
                                                                                      "train_pbr"))
                     for f in files if os.path.basename(root) == "rgb")
        assert len(rgb) == len(labels) and all(f.endswith(".jpg") for f in rgb)  # the toolkit's train_pbr ext
        for path, (_, png, _) in zip(rgb, labels):
            img = _read_gray(path)
            gray = cv2_decode(png)
            assert img.shape == gray.shape + (3,)  # three channels, the gray replicated
            assert np.array_equal(img[..., 0], img[..., 1]) and np.array_equal(img[..., 0], img[..., 2])
            assert np.abs(img[..., 0].astype(float) - gray).mean() < 2.0  # JPEG quality 95
        truncated = 0
        for (uv, mask, inf, cam), (lab, _, fmask) in zip(got, labels):
            assert np.abs(uv - np.asarray(lab["corners_px"])).max() < 1e-3
            assert np.array_equal(mask > 0, fmask > 0) and set(np.unique(mask)) <= {0, 255}
            assert inf["px_count_visib"] == np.count_nonzero(fmask)
            ys, xs = np.nonzero(fmask)
            assert inf["bbox_visib"] == [xs.min(), ys.min(), xs.max() - xs.min(), ys.max() - ys.min()]
            x, y, w, h = inf["bbox_obj"]  # the whole projected model holds the visible part
            assert x <= xs.min() + 1 and y <= ys.min() + 1 and x + w >= xs.max() - 1 and y + h >= ys.max() - 1
            cut = x < 0 or y < 0 or x + w >= fmask.shape[1] or y + h >= fmask.shape[0]  # the image cuts the model
            assert inf["px_count_all"] >= inf["px_count_visib"] and (cut or inf["visib_fract"] == 1.0)
            truncated += inf["px_count_all"] > inf["px_count_visib"]  # the toolkit counts the part beyond it
            assert inf["visib_fract"] == pytest.approx(inf["px_count_visib"] / inf["px_count_all"])
            assert cam["depth_scale"] == pytest.approx(2.0)  # the factory's 0.002 m per unit, in mm
        assert case == "seq" or truncated  # 1024 px random views of ENVISAT: the image cuts some (seed 21)
    verts = _ply_vertices(os.path.join(exports["rand", "bop"], "models", "obj_000001.ply"))
    info = json.load(open(os.path.join(exports["rand", "bop"], "models", "models_info.json")))["1"]
    assert verts.max(axis=0)[0] == pytest.approx(5800.0, abs=0.01)  # the MERIS box's front, mm
    assert verts.min(axis=0)[0] == pytest.approx(-22000.0, abs=0.01)  # the array's far edge
    assert info["size_x"] == pytest.approx(27800.0, abs=0.01) and "symmetries_discrete" not in info
    assert info["diameter"] == pytest.approx(_brute_diameter(verts), rel=1e-9)
    props, ev, faces = _ply_read(os.path.join(exports["rand", "bop"], "models_eval", "obj_000001.ply"))
    assert props == ["x", "y", "z", "nx", "ny", "nz"] and np.allclose(ev[:, :3], verts, atol=1e-6)
    normals = ev[:, 3:]
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    face_n = np.cross(ev[faces[:, 1], :3] - ev[faces[:, 0], :3], ev[faces[:, 2], :3] - ev[faces[:, 0], :3])
    assert np.all(np.einsum("fk,fck->fc", face_n, normals[faces]) > 0)  # each leans outward with its triangles
    assert json.load(open(os.path.join(exports["rand", "bop"], "models_eval", "models_info.json")))["1"] == info


def _read_gray(path):
    import cv2

    return cv2.imread(path, cv2.IMREAD_UNCHANGED)


def cv2_decode(data):
    import cv2

    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)


def _ply_read(path):
    """(vertex property names, (V, P) vertex values, (F, 3) triangles) of an ASCII PLY, as its header says."""
    with open(path) as fh:
        lines = fh.read().splitlines()
    start = lines.index("end_header") + 1
    n_v = int(next(ln for ln in lines if ln.startswith("element vertex")).split()[-1])
    n_f = int(next(ln for ln in lines if ln.startswith("element face")).split()[-1])
    vertex_head = lines[lines.index(f"element vertex {n_v}") + 1:]
    props = [ln.split()[-1] for ln in vertex_head[:next(i for i, ln in enumerate(vertex_head)
                                                         if not ln.startswith("property"))]]
    values = np.array([[float(v) for v in ln.split()] for ln in lines[start:start + n_v]])
    faces = np.array([[int(v) for v in ln.split()[1:]] for ln in lines[start + n_v:start + n_v + n_f]])
    return props, values, faces


def _ply_vertices(path):
    return _ply_read(path)[1][:, :3]


def _brute_diameter(points):
    from scipy.spatial.distance import pdist

    return float(pdist(points).max())


def _cube():
    """A cube of half-size 1 as 12 triangles, counter-clockwise seen from outside (its faces' normals by hand)."""
    v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return v, np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])


def test_vertex_normals_point_outward_with_unit_length():
    v, f = _cube()
    n = vertex_normals(v, f)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    assert np.array_equal(np.sign(n), np.sign(v))  # a corner's normal points out between its three faces
    lone = vertex_normals(np.vstack([v, [[5.0, 0.0, 0.0]]]), f)  # a vertex no triangle uses
    assert np.allclose(np.linalg.norm(lone, axis=1), 1.0)


def test_bop_model_info_diameter_exact_and_linear_memory():
    import time
    import tracemalloc

    rng = np.random.default_rng(5)
    for pts in (rng.normal(size=(400, 3)) * [3000.0, 700.0, 90.0],  # a flat-ish cloud: most points inside the hull
                np.c_[rng.normal(size=(300, 2)) * 1000.0, np.zeros(300)],  # flat: no 3-D hull, every point compared
                _cube()[0] * 500.0):
        info = bop_model_info(pts)
        assert info["diameter"] == pytest.approx(_brute_diameter(pts), rel=1e-12)
        assert info["size_x"] == pytest.approx(np.ptp(pts[:, 0]))
    sphere = rng.normal(size=(20_000, 3))
    sphere *= 10_000.0 / np.linalg.norm(sphere, axis=1)[:, None]  # every vertex on the hull: the worst case
    tracemalloc.start()
    t0 = time.perf_counter()
    d = bop_model_info(sphere)["diameter"]
    seconds = time.perf_counter() - t0
    peak_mb = tracemalloc.get_traced_memory()[1] / 1e6
    tracemalloc.stop()
    assert 19_990.0 < d <= 20_000.0 + 1e-6
    assert peak_mb < 64  # a V x V x 3 float64 difference array would be 9,600 MB
    assert seconds < 30


# --- COCO: pycocotools -----------------------------------------------------------------------------------------

def coco_codes(lab):
    vis, frame = np.asarray(lab["visible"]), np.asarray(lab["in_frame"])
    return np.where(frame & vis, 2, np.where(frame, 1, 0))


@pytest.mark.parametrize("case", ["rand", "seq"])
def test_coco_keypoints_and_oks(datasets, exports, case):
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    folder = exports[case, "coco"]
    labels = labels_of(datasets[case])
    seen = 0
    for split in ("train", "val"):
        coco = COCO(os.path.join(folder, "annotations", f"keypoints_{split}.json"))
        cat = coco.loadCats(coco.getCatIds())[0]
        assert cat["keypoints"] == list(CORNER_NAMES)
        assert sorted(tuple(sorted(p)) for p in cat["skeleton"]) == sorted((min(a, b) + 1, max(a, b) + 1)
                                                                             for a, b in EDGES)  # the box's 12
        for img in coco.loadImgs(coco.getImgIds()):
            lab, _, mask = labels[int(os.path.splitext(os.path.basename(img["file_name"]))[0])]
            assert os.path.exists(os.path.join(folder, "images", img["file_name"]))
            ann = coco.loadAnns(coco.getAnnIds(imgIds=img["id"]))[0]
            kp = np.asarray(ann["keypoints"], float).reshape(-1, 3)
            codes = coco_codes(lab)
            assert np.array_equal(kp[:, 2], codes)
            inside = codes > 0
            assert np.abs(kp[inside, :2] - np.asarray(lab["corners_px"])[inside]).max() < 0.01
            assert np.all(kp[~inside, :2] == 0) and ann["num_keypoints"] == inside.sum()
            ys, xs = np.nonzero(mask)
            assert ann["bbox"] == [xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1]
            seen += 1
        results = [{**a, "score": 1.0} for a in coco.loadAnns(coco.getAnnIds())]
        ev = COCOeval(coco, coco.loadRes(results), "keypoints")
        ev.params.kpt_oks_sigmas = np.full(8, 0.025)
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
        assert ev.stats[0] == pytest.approx(1.0)
    assert seen == len(labels)


# --- YOLO-pose: Ultralytics's rows -------------------------------------------------------------------------------

def load_data_yaml(folder, elsewhere, monkeypatch):
    """data.yaml as Ultralytics reads it, from another working folder: (the dict, its `path`)."""
    import yaml  # PyYAML: installed with dask (a dependency), the parser Ultralytics uses

    monkeypatch.chdir(elsewhere)
    with open(os.path.join(folder, "data.yaml"), encoding="utf-8") as fh:
        data = yaml.safe_load(fh)
    return data, data["path"]


@pytest.mark.parametrize("case", ["rand", "seq"])
def test_yolo_pose_rows(datasets, exports, case, tmp_path, monkeypatch):
    folder = exports[case, "yolo-pose"]
    labels = labels_of(datasets[case])
    data, root = load_data_yaml(folder, tmp_path, monkeypatch)
    assert os.path.isabs(root) and os.path.samefile(root, folder) and ".tmp-export-" not in root  # the final folder
    for split in ("train", "val"):
        assert os.path.isdir(os.path.join(root, data[split])) and os.listdir(os.path.join(root, data[split]))
    assert data["kpt_shape"] == [8, 3] and "flip_idx" not in data  # chiral: Ultralytics then does not flip
    assert data["kpt_oks_sigmas"] == [0.025] * 8 and data["kpt_names"] == {0: list(CORNER_NAMES)}
    assert data["names"] == {0: "envisat"}
    seen = 0
    for split in ("train", "val"):
        for name in sorted(os.listdir(os.path.join(folder, "labels", split))):
            i = int(os.path.splitext(name)[0])
            lab, _, mask = labels[i]
            h, w = mask.shape
            row = np.array(open(os.path.join(folder, "labels", split, name)).read().split(), float)
            assert row.size == 5 + 8 * 3 and row[0] == 0
            kp = row[5:].reshape(8, 3)
            codes = coco_codes(lab)
            assert np.array_equal(kp[:, 2], codes)
            inside = codes > 0
            uv = kp[:, :2] * [w, h]
            expected = np.clip(np.asarray(lab["corners_px"]), 0.0, [w, h])  # clamped: no negative value
            assert np.abs(uv[inside] - expected[inside]).max() < 0.01
            assert np.all(kp[~inside] == 0)
            ys, xs = np.nonzero(mask)
            box = row[1:5] * [w, h, w, h]
            assert box == pytest.approx([(xs.min() + xs.max() + 1) / 2, (ys.min() + ys.max() + 1) / 2,
                                         xs.max() - xs.min() + 1, ys.max() - ys.min() + 1], abs=1e-3)
            assert os.path.exists(os.path.join(folder, "images", split, f"{i:06d}.png"))
            seen += 1
    assert seen == len(labels)


def test_yolo_pose_row_clamps_a_keypoint_left_of_the_first_pixel_centre():
    """A keypoint in the frame at u = -0.3 px (the frame starts at -0.5): Ultralytics drops an image whose label
    holds a negative value, so the row writes it at 0 (a 0.3 px move); the rest stays u / W."""
    from envisat_pose.datagen.export_formats import yolo_row

    label = {"keypoints_px": [[-0.3, 10.0], [63.2, 31.5], [90.0, 5.0]], "in_frame": [True, True, False],
             "visible": [True, False, True]}
    row = np.array(yolo_row(label, (0, 0, 63, 31), 64, 32).split(), float)
    assert row.min() >= 0.0 and row[1:5].max() <= 1.0
    assert row[5:].tolist() == pytest.approx([0.0, 10.0 / 32, 2, 63.2 / 64, 31.5 / 32, 1, 0, 0, 0], abs=1e-7)
    assert "clamped to [0, 1]" in readme_of("yolo-pose")


def test_a_sequence_speedplus_readme_names_the_files_its_export_holds():
    """A sequence's SPEED+ export holds `<name>/<name>.json`, no synthetic/train.json: its README's SPNv2 command
    names the files there are (random views keep theirs)."""
    text = readme_of("speedplus", "sequence")
    assert "--jsonfile synthetic/" not in text and "`seq/seq.json`" in text
    assert "cp /data/out/seq/seq.json /data/out/seq/synthetic/" in text and "--jsonfile seq/synthetic/seq.json" in text
    assert "--jsonfile synthetic/train.json" in readme_of("speedplus", "random")


def test_every_readme_says_visible_is_the_labels_ray_cast():
    """The labels' `visible` comes from ray casts through the target's drawn geoms (Target.visible), not from the
    rendered depth: each format's README says so."""
    for fmt in ("speedplus", "coco", "bop", "yolo-pose"):
        text = readme_of(fmt)
        assert "rendered depth;" not in text and "meets no opaque drawn" in text


def test_the_coco_readme_snippet_imports_every_name_it_uses():
    """The README's pycocotools lines, run as they stand, define every name before its use (np included)."""
    import ast
    import builtins

    text = readme_of("coco")
    lines = text[text.index("## Run it"):].splitlines()[1:]
    code = "\n".join(ln[4:] for ln in lines[:next(i for i, ln in enumerate(lines) if not ln.startswith("    "))])
    tree = ast.parse(code)
    bound = {a.asname or a.name for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom)) for a in n.names}
    bound |= {n.id for n in ast.walk(tree) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store)}
    used = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load)}
    assert "np" in used and used - bound - set(dir(builtins)) == set()


def readme_of(fmt, mode="random", **manifest):
    """The README an export of a small ENVISAT dataset writes (its text only: no dataset needed)."""
    from envisat_pose.pipelines.datasets.export_layouts import Layout
    from envisat_pose.pipelines.datasets.export_readme import readme_text

    layout = Layout(fmt=fmt, ext="png", mode=mode, sequence="seq", target="envisat", keypoint_names=CORNER_NAMES,
                    keypoints_T_m=[], outline_T_m=[], depth_scale_mm=None, skeleton=[])
    K = np.array([[120.0, 0.0, 31.5], [0.0, 120.0, 31.5], [0.0, 0.0, 1.0]])
    return readme_text(layout, K, 64, 1e-5, {"root_seed": 0, "num_images": 4, **manifest}, "/data/out")


# --- safety -----------------------------------------------------------------------------------------------------

def _left_behind(parent):
    return [n for n in os.listdir(parent) if n.startswith(".tmp-export-")]


def test_interrupted_export_leaves_nothing(datasets, tmp_path):
    out = tmp_path / "deep" / "out"

    def interrupt(_):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        export_dataset(datasets["rand"], str(out), ExportConfig("bop"), progress=False, on_shard=interrupt)
    assert os.listdir(tmp_path) == []  # neither the folder, its staging folder, nor the parent made for it


def test_damaged_shard_refused_then_skipped(datasets, tmp_path, capsys):
    src = tmp_path / "src"
    shutil.copytree(datasets["rand"], src)
    with open(src / "shard-000001.tar", "r+b") as fh:
        fh.seek(2000)
        byte = fh.read(1)
        fh.seek(2000)
        fh.write(bytes([byte[0] ^ 0xFF]))
    out = tmp_path / "out"
    rc = envisat_main(["dataset", "export", str(src), "--format", "coco", "--out", str(out), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "shard-000001.tar" in err[0] and "--skip-damaged" in err[0]
    assert not out.exists() and _left_behind(tmp_path) == []
    rc = envisat_main(["dataset", "export", str(src), "--format", "coco", "--out", str(out), "--quiet",
                       "--skip-damaged", "--workers", "2"])
    assert rc == 0 and "skipped 1 damaged shard(s): shard-000001.tar" in capsys.readouterr().out
    record = json.load(open(out / "export.json"))
    assert record["skipped_damaged_shards"] == ["shard-000001.tar"] and sum(record["images"].values()) == 3


def test_existing_out_refused_and_kept(datasets, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("keep me")
    rc = envisat_main(["dataset", "export", datasets["seq"], "--format", "yolo-pose", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--out" in err[0] and "not empty" in err[0]
    assert os.listdir(out) == ["mine.txt"] and _left_behind(tmp_path) == []


def test_bad_arguments_one_line(datasets, tmp_path):
    with pytest.raises(InputError, match="src '.*nowhere': no such folder"):
        export_dataset(str(tmp_path / "nowhere"), str(tmp_path / "o"), ExportConfig("bop"))
    with pytest.raises(InputError, match="SHIRT"):
        export_dataset(datasets["seq"], str(tmp_path / "o"), ExportConfig("speedplus", val_fraction=0.2))
    assert os.listdir(tmp_path) == []


def test_jpg_images(datasets, tmp_path):
    out = export_dataset(datasets["seq"], str(tmp_path / "j"), ExportConfig("speedplus", image_format="jpg"),
                         progress=False).out_dir
    entries = json.load(open(os.path.join(out, "seq", "seq.json")))
    first = _read_gray(os.path.join(out, "seq", "synthetic", "images", entries[0]["filename"]))
    assert entries[0]["filename"].endswith(".jpg") and first.shape == (512, 512)


def test_another_target_exports_its_own_keypoints(tmp_path, monkeypatch):
    """A shipped non-ENVISAT target (the 3U CubeSat, 12 keypoints): every format carries its K keypoints and its
    name, and the poses reproject its own 3-D keypoints onto the labels."""
    from envisat_pose.geometry import model_path
    from envisat_pose.target import load_target

    cube = os.path.join(os.path.dirname(model_path()), "cubesat_3u.xml")
    src = str(tmp_path / "cube")
    run_generate(from_dict(GenerateConfig, {"target": cube, "num_images": 3, "shard_size": 3, "resolution_px": 256,
                                            "seed": 3, "random": {"range_min_m": 4.0, "range_max_m": 7.0,
                                                                  "keepout_margin_m": 1.0}}), src)
    labels = [lab for _, lab, _ in iter_samples(src)]
    names = labels[0]["keypoint_names"]
    assert len(names) == 12
    outs = {f: export_dataset(src, str(tmp_path / f), ExportConfig(f, val_fraction=0.0), progress=False).out_dir
            for f in FORMATS}
    camera, points, entries, _ = speedplus_errors_px(outs["speedplus"])
    assert points.shape == (3, 12)
    for e, lab in zip(sorted(entries, key=lambda e: e["filename"]), labels):
        uv = spnv2_project(e["q_vbs2tango_true"], e["r_Vo2To_vbs_true"], camera, points)
        assert np.abs(uv - np.asarray(lab["keypoints_px"])).max() < 1e-3
    coco = json.load(open(os.path.join(outs["coco"], "annotations", "keypoints_train.json")))
    assert coco["categories"][0]["name"] == "cubesat_3u" and coco["categories"][0]["keypoints"] == names
    skeleton = coco["categories"][0]["skeleton"]
    assert skeleton and skeleton == [[a + 1, b + 1] for a, b in load_target(cube).skeleton]
    assert all(1 <= i <= 12 for pair in skeleton for i in pair)
    for ann, lab in zip(coco["annotations"], labels):
        kp = np.asarray(ann["keypoints"], float).reshape(-1, 3)
        inside = kp[:, 2] > 0
        assert kp.shape == (12, 3) and np.abs(kp[inside, :2] - np.asarray(lab["keypoints_px"])[inside]).max() < 0.01
    data, _ = load_data_yaml(outs["yolo-pose"], tmp_path, monkeypatch)
    assert data["kpt_shape"] == [12, 3] and data["kpt_oks_sigmas"] == [0.025] * 12 and data["kpt_names"][0] == names
    assert data["flip_idx"] == list(load_target(cube).mirror_perm)  # its mirrors: a flipped image relabelled
    bop_kp = json.load(open(os.path.join(outs["bop"], "models", "keypoints_3d.json")))["1"]
    assert bop_kp["names"] == names and np.allclose(np.asarray(bop_kp["points_mm"]).T, points * 1000.0)
    # its half-turns, as the BOP toolkit reads them (misc.get_symmetry_transformations: 4 x 4 row-major, mm): each
    # a proper rotation that maps the exported model's vertices and keypoints onto themselves
    sym = json.load(open(os.path.join(outs["bop"], "models", "models_info.json")))["1"]["symmetries_discrete"]
    verts = _ply_vertices(os.path.join(outs["bop"], "models", "obj_000001.ply"))
    kp_mm = np.asarray(bop_kp["points_mm"])
    assert len(sym) == 3
    for m in sym:
        T = np.asarray(m).reshape(4, 4)
        R, tvec = T[:3, :3], T[:3, 3]
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0 and np.allclose(tvec, 0)
        for pts in (verts, kp_mm):
            moved = pts @ R.T
            assert np.min(np.linalg.norm(moved[:, None] - pts[None], axis=2), axis=1).max() < 1e-3  # mm
    assert json.load(open(os.path.join(outs["bop"], "export.json")))["target"]["name"] == "cubesat_3u"


def test_a_moved_target_file_is_given_with_target(tmp_path, monkeypatch):
    """A dataset generated from a target file named relative to the folder it ran in: read from elsewhere, the
    recorded path is gone, and `--target` gives the file (checked against the recorded sha256); an edited file is
    refused. The export's keypoints are the file's."""
    from envisat_pose.geometry import model_path

    home = tmp_path / "home"
    home.mkdir()
    shutil.copy(os.path.join(os.path.dirname(model_path()), "cubesat_3u.xml"), home / "sat.xml")
    monkeypatch.chdir(home)
    src = str(tmp_path / "cube")
    run_generate(from_dict(GenerateConfig, {"target": "sat.xml", "num_images": 2, "shard_size": 2,
                                            "resolution_px": 128, "seed": 4}), src, progress=False)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match="sat.xml"):
        export_dataset(src, str(tmp_path / "lost"), ExportConfig("coco", val_fraction=0.0), progress=False)
    out = export_dataset(src, str(tmp_path / "found"), ExportConfig("coco", val_fraction=0.0,
                                                                    target=str(home / "sat.xml")), progress=False)
    coco = json.load(open(os.path.join(out.out_dir, "annotations", "keypoints_train.json")))
    assert len(coco["categories"][0]["keypoints"]) == 12 and len(coco["annotations"]) == 2
    # export.json names the target as the manifest does (the file as given, here the one given in its place; its
    # name, sha256 and keypoints) and the source as a record that travels names a dataset (no path of this machine)
    manifest = json.load(open(os.path.join(src, "manifest.json")))
    record = json.load(open(os.path.join(out.out_dir, "export.json")))
    assert record["target"] == {**manifest["target"], "file": str(home / "sat.xml")}
    assert record["source"] == dataset_ref(src) and record["source"].startswith("cube (manifest sha256 ")
    monkeypatch.chdir(home)  # the recorded path found: the record is the manifest's, and the file holds no path here
    out = export_dataset(src, str(tmp_path / "here"), ExportConfig("coco", val_fraction=0.0), progress=False)
    text = open(os.path.join(out.out_dir, "export.json")).read()
    assert json.loads(text)["target"] == manifest["target"] and find_absolute_paths(text) == []
    (home / "sat.xml").write_text((home / "sat.xml").read_text().replace("<mujoco", "<!-- edited -->\n<mujoco", 1))
    with pytest.raises(InputError, match="not the target file of the dataset .*unchanged since the dataset was generated"):
        export_dataset(src, str(tmp_path / "edited"), ExportConfig("coco", val_fraction=0.0,
                                                                   target=str(home / "sat.xml")), progress=False)


def test_the_outline_box_spans_the_pixel_centres_and_bops_object_box_is_not_clipped():
    """The projected outline (-10.3, 5.2)-(20.7, 30.9) on a 16 x 16 image covers the pixel centres x -10..20,
    y 6..30 (ceil of the least, floor of the largest), clipped to x 0..15, y 6..15; BOP's bbox_obj keeps the part
    outside the image ([x, y, w, h] with w = x_max - x_min, as the BOP toolkit's calc_2d_bbox), bbox_visib is the
    mask's."""
    from envisat_pose.datagen.export_formats import bop_gt_info, outline_box

    outline = np.array([[-10.3, 5.2], [20.7, 30.9], [3.0, 12.5]])
    assert outline_box(outline, 16, 16, clip=False) == (-10, 6, 20, 30)
    assert outline_box(outline, 16, 16, clip=True) == (0, 6, 15, 15)
    assert outline_box(outline + 100.0, 16, 16, clip=True) is None  # wholly outside
    mask = np.zeros((16, 16), np.uint8)
    mask[6:16, 0:16] = 1
    info = bop_gt_info(mask, outline)
    assert info["bbox_obj"] == [-10, 6, 30, 24] and info["bbox_visib"] == [0, 6, 15, 9]
    assert info["px_count_visib"] == 160


def _label(points_px_z=1.0):
    """A label whose camera sees T's x, y as pixel coordinates at depth 1 m: R = I, t = (0, 0, 1), K = I."""
    return {"R_cam_from_target": np.eye(3).tolist(), "t_cam_from_target_m": [0.0, 0.0, points_px_z],
            "K": np.eye(3).tolist()}


def test_bops_visib_fract_counts_the_silhouette_the_image_cuts_off():
    """The BOP toolkit's calc_gt_info counts the whole silhouette on a 3 W x 3 H canvas in px_count_all, so a
    target the image cuts has visib_fract < 1 (loaders drop views below 0.1). A rectangle (-4.6, 2.2)-(9.8, 6.9) on
    a 16 x 16 image covers the centres x -4..9, y 3..6: 56 pixels, 40 in the image, 16 beyond it."""
    from envisat_pose.datagen.export_formats import bop_gt_info, truncated_px_count

    rect = np.array([[-4.6, 2.2, 0.0], [9.8, 2.2, 0.0], [9.8, 6.9, 0.0], [-4.6, 6.9, 0.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    assert truncated_px_count(rect, faces, _label(), 16, 16) == 16
    mask = np.zeros((16, 16), np.uint8)
    mask[3:7, 0:10] = 1
    info = bop_gt_info(mask, rect[:, :2], truncated_px_count(rect, faces, _label(), 16, 16))
    assert info["px_count_all"] == 56 and info["px_count_visib"] == info["px_count_valid"] == 40
    assert info["visib_fract"] == pytest.approx(40 / 56)
    inside = rect + [6.0, 0.0, 0.0]  # x 1.4..15.8: the centres 2..15, all in the image
    assert truncated_px_count(inside, faces, _label(), 16, 16) == 0
    assert truncated_px_count(rect + [100.0, 0.0, 0.0], faces, _label(), 16, 16) == 0  # beyond the canvas too


def test_the_truncated_count_matches_a_pixel_centre_test_and_clips_behind_the_camera():
    """Random triangles over the canvas against matplotlib's point-in-polygon test of every pixel centre; a
    triangle reaching behind the camera counts what lies in front of it (no wrap-around), at most the canvas."""
    from matplotlib.path import Path

    from envisat_pose.datagen.export_formats import truncated_px_count

    rng = np.random.default_rng(5)
    w, h = 12, 10
    pts = np.c_[rng.uniform(-1.4 * w, 2.4 * w, (9, 1)), rng.uniform(-1.4 * h, 2.4 * h, (9, 1)), np.zeros((9, 1))]
    faces = np.arange(9).reshape(3, 3)
    ys, xs = np.mgrid[-h:2 * h, -w:2 * w]
    centres = np.c_[xs.ravel(), ys.ravel()]
    covered = np.zeros(len(centres), bool)
    for f in faces:
        covered |= Path(pts[f, :2]).contains_points(centres)
    covered &= ~((centres[:, 0] >= 0) & (centres[:, 0] < w) & (centres[:, 1] >= 0) & (centres[:, 1] < h))
    assert truncated_px_count(pts, faces, _label(), w, h) == int(covered.sum())
    behind = np.array([[-3.0, -3.0, 0.5], [3.0, -3.0, 0.5], [0.0, 3.0, -2.0]])  # the camera's plane cuts it
    n = truncated_px_count(behind, np.array([[0, 1, 2]]), _label(0.0), w, h)
    assert 0 < n <= 8 * w * h
