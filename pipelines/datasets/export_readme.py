"""The README.md an export writes into its folder: the dataset's numbers and the conventions of its format, so
the folder explains itself wherever it is copied (docs/formats.md is the project's page on the formats)."""

from __future__ import annotations

import os
import shlex

import numpy as np

from envisat_pose.datagen.export_formats import OKS_SIGMA

_COMMON = """\
## Conventions
- Camera frame: OpenCV's: x right, y down, z along the boresight (MuJoCo's camera looks along -z with y up; the
  exporter converts). Target body frame: the MJCF body `target`'s frame (origin at the centre of mass).
- Pose: x_cam = R x_body + t. R is R_cam_from_target; t is the target's origin in the camera frame.
- Pixels: pixel centres at integer coordinates (OpenCV's convention); the principal point of an N-px image is
  ((N - 1) / 2, (N - 1) / 2). Keypoint coordinates are the projections of the keypoints' 3-D positions.
- Keypoints ({k}, in this order): {names}. Visible = the ray from the camera to it meets no opaque drawn
  geom of the target first, and it is in-frame; in-frame = its projection falls within [-0.5, N - 0.5) on both
  axes, in front of the camera.
- Intrinsics: fx = fy = {f:.6f} px, cx = {cx:.1f}, cy = {cy:.1f}, {n} x {n} px, no distortion.
"""

_FORMAT = {
    "speedplus": """\
## SPEED+ layout (SPNv2 and its descendants)
- `camera.json`: Nu, Nv (px); ppx, ppy: pixel pitch ({pitch:.4g} m); fx, fy: focal length in metres (= f_px x
  pitch); ccx, ccy: principal point (px); cameraMatrix; distCoeffs (5 zeros, OpenCV order); horizontalFOV (deg).
- Random views: `synthetic/images/`, `synthetic/masks/`, `synthetic/train.json`, `synthetic/validation.json` (a
  seeded split). A sequence: `<name>/synthetic/images/`, `<name>/synthetic/masks/`, `<name>/<name>.json` (frames
  in time order), `<name>/metadata.json` (each frame's time t_s, s) - the SHIRT layout.
- `masks/`: one 8-bit PNG per image, the image's name with .png (`img000001.png`, as SPNv2's preprocess.py
  looks it up), 255 = target, 0 = background (SPNv2 thresholds at 128: 0/1 masks would read as empty). Present
  when the dataset has masks (`write_mask`, on by default).
- Each entry: `filename`; `q_vbs2tango_true`: unit quaternion, scalar first (w, x, y, z), Hamilton's product,
  of R with x_cam = R(q) x_body + r (w >= 0); `r_Vo2To_vbs_true`: r, metres, camera frame.
- `models/keypoints.mat`: variable `tango3Dpoints`, 3 x K, metres, body frame (as SPNv2's loader reads it).
""",
    "coco": """\
## COCO keypoints layout
- `images/<split>/`, `annotations/keypoints_<split>.json` with `images` (id, file_name relative to `images/`,
  width, height, and K), `annotations` (bbox [x, y, w, h] of {box_source} over whole pixels: pixel i covers
  [i, i + 1]; area: {coco_area}; iscrowd 0; keypoints [x, y, v] per keypoint; num_keypoints: count of v > 0;
  pose: R_cam_from_target, q_cam_from_target_wxyz, t_cam_from_target_m), `categories` (keypoint names,
  skeleton: the target's keypoint pairs joined along its edges (its MJCF's sharp edges), 1-based;
  keypoints_3d_m: the keypoints in the body frame).
- v = 2 visible, 1 in the frame but hidden, 0 outside the frame (then x = y = 0). x, y: the pixel coordinates
  above (centres at integers: COCO's keypoint convention as detectron2 reads it).
- Images with {no_target} have no annotation.
{box_note}- OKS: a sigma of {sigma:g} per keypoint is suggested (corners are sharp; COCO's eyes use 0.025): a keypoint
  scores 0.5 at an error of 0.059 sqrt(area).

## Run it
    import numpy as np
    from pycocotools.coco import COCO; from pycocotools.cocoeval import COCOeval
    gt = COCO({coco_gt_py})   # images: {folder}/images/ + file_name
    ev = COCOeval(gt, gt.loadRes("predictions.json"), "keypoints"); ev.params.kpt_oks_sigmas = np.full({k}, {sigma:g})
  detectron2: `register_coco_instances({coco_name_py}, {{}}, {coco_train_py},
  {coco_images_py})`, metadata keypoint_names (above) and {coco_flip}.
""",
    "bop": """\
## BOP layout (one object, obj_id 1)
- `camera.json`: cx, cy, fx, fy (px), width, height, depth_scale (mm per depth unit).
- `models/obj_000001.ply`: the target's geoms as triangles, millimetres, body frame; `models/models_info.json`:
  diameter and extent (mm), and {bop_symmetries}. `models/keypoints_3d.json` (an extra):
  the keypoints in mm. `models_eval/obj_000001.ply`: the same triangles with per-vertex normals (nx ny nz: each
  vertex's triangles' normals weighted by their areas, unit length; not resampled), and its `models_info.json`.
- `train_pbr/NNNNNN/` (random views: 1000 images a scene; a sequence: one scene): `rgb/NNNNNN.jpg` (the gray
  image replicated into three channels, JPEG quality 95: the BOP toolkit's extension for PBR splits, whatever
  --image-format says), `depth/` (16-bit, z along the boresight, x depth_scale mm; 0 = no target),
  `mask/<im>_000000.png` (the object's full silhouette) and `mask_visib/<im>_000000.png` (its visible part):
  255 = target, the same file here, one object with nothing to occlude it; `scene_gt.json` (cam_R_m2c
  row-major, cam_t_m2c mm), `scene_camera.json` (cam_K row-major, depth_scale), `scene_gt_info.json` (bbox_obj:
  the projected model, may leave the image; bbox_visib: the mask; both [x, y, w, h] with w = x_max - x_min over
  pixel indices, as the BOP toolkit; px_count_visib = px_count_valid = the mask's pixels; px_count_all adds the
  silhouette beyond the image on the toolkit's 3 W x 3 H canvas, so visib_fract < 1 where the image cuts it).

## Run it
    from bop_toolkit_lib import inout
    gt = inout.load_scene_gt({bop_gt_py})
    model = inout.load_ply({bop_ply_py})   # pts (mm), normals, faces
  The toolkit's scripts (scripts/calc_gt_info.py, calc_gt_masks.py, eval_bop19_pose.py) find a dataset by name
  in bop_toolkit_lib/dataset_params.py: add `{name}` there (obj_ids [1], {bop_symmetric_ids}, im_size
  ({n}, {n}), scene ids from train_pbr/) and set `datasets_path` in bop_toolkit_lib/config.py to {parent}.
""",
    "yolo-pose": """\
## Ultralytics YOLO-pose layout
- `images/<split>/`, `labels/<split>/` (one .txt per image; empty: {no_target}), `data.yaml`: `path` this
  folder's absolute path as exported (works from any working folder; moved: edit it), kpt_shape [{k}, 3],
  `kpt_oks_sigmas` {sigma:g} per keypoint (Ultralytics releases that read it score OKS with it, others with 1/K:
  a keypoint scores 0.5 at an error of 0.059 sqrt(area)); {yolo_flip}.
- A row: class 0, box centre x, y and width, height ({box_source}'s whole pixels), then x y v per keypoint, all
  divided by the image's width (x) or height (y); x = u / W with u the pixel coordinate above (centres at
  integers, as Ultralytics's own COCO converter divides), clamped to [0, 1] (Ultralytics drops an image with a
  negative value: a keypoint in the frame within half a pixel of its left or top edge, u in [-0.5, 0), is
  written at 0, a move of at most 0.5 px); v = 2 visible, 1 hidden, a keypoint outside the frame `0 0 0`.
{box_note}
## Run it
    yolo pose train {yolo_data_sh} model=yolov8n-pose.pt imgsz={n}
""",
}


_SPNV2_RUN = {
    "random": """
## Run it (SPNv2, random views)
    python3 tools/preprocess.py --cfg experiments/offline_train_full_config.yaml --jsonfile synthetic/train.json \\
        DATASET.ROOT {parent_sh} DATASET.DATANAME {name_sh} DATASET.KEYPOINTS {keypoints_sh} \\
        DATASET.NUM_KEYPOINTS {k} DATASET.IMAGE_SIZE "[{n}, {n}]"
  (again with `--jsonfile synthetic/validation.json`), then `tools/train.py` with the same overrides. SPNv2 reads
  the SPEED+ layout only when DATANAME contains `speedplus` (name the folder so), and its preprocess.py packs 11
  keypoints plus the origin (24 values): for another K that line needs 2 (K + 1) (K = {k} here).
""",
    "sequence": """
## Run it (SPNv2, a sequence)
  This folder holds no `synthetic/train.json` or `synthetic/validation.json`: the labels are `{seq}/{seq}.json`,
  the images `{seq}/synthetic/images/`, the masks `{seq}/synthetic/masks/`. SPNv2's preprocess.py reads a SHIRT
  trajectory when DATANAME contains `shirt` (name the folder so), its labels from `--jsonfile
  <trajectory>/<domain>/<file>` and its images from `<trajectory>/<domain>/images/`, so the labels go beside
  the images first:
    cp {seq_json_sh} {seq_synthetic_sh}
    python3 tools/preprocess.py --cfg experiments/offline_train_full_config.yaml \\
        --jsonfile {seq}/synthetic/{seq}.json DATASET.ROOT {parent_sh} DATASET.DATANAME {name_sh} \\
        DATASET.KEYPOINTS {keypoints_sh} DATASET.NUM_KEYPOINTS {k} DATASET.IMAGE_SIZE "[{n}, {n}]"
  Its preprocess.py packs 11 keypoints plus the origin (24 values): for another K that line needs 2 (K + 1)
  (K = {k} here).
""",
}


def _box_texts(masks: bool) -> dict[str, str]:
    """Where COCO's and YOLO-pose's boxes come from: the target's mask, or, for a dataset generated without masks
    (write_mask = false), the projected model (export_layouts._box)."""
    if masks:
        return {"box_source": "the target's mask", "coco_area": "the mask's pixel count",
                "no_target": "no target pixel", "box_note": ""}
    return {"box_source": "the projected model", "coco_area": "the box's w x h (no mask to count)",
            "no_target": "no projected model in the frame",
            "box_note": "- Boxes: this dataset has no masks (generated with write_mask = false), so each box is the\n"
                        "  projected model's: the pixels whose centres the projections of its vertices span, clipped\n"
                        "  to the image.\n"}


def _symmetry_texts(layout) -> dict[str, str]:
    """What BOP's files and scripts are told of the target's symmetries (layout.symmetric: models_info.json holds
    symmetries_discrete)."""
    if not layout.symmetric:
        return {"bop_symmetries": "no symmetries (no rotation of the target looks the same in an image)",
                "bop_symmetric_ids": "no symmetric objects"}
    return {"bop_symmetries": "`symmetries_discrete` (the rotations that no image tells from the identity: shape "
                              "and materials kept, 4 x 4 row-major, mm)",
            "bop_symmetric_ids": "symmetric_obj_ids [1]"}


def _flip_texts(layout) -> dict[str, str]:
    """What YOLO's and detectron2's left-right flip are told: the mirror symmetry's keypoint pairs, or that the
    target is chiral (a mirrored image shows another object) and the flip is off."""
    if layout.flip_idx is None:
        chiral = "the target is chiral, a mirrored image shows another object"
        return {"yolo_flip": f"no flip_idx: {chiral}, and without flip_idx Ultralytics turns its left-right flip "
                             "off",
                "coco_flip": f'keypoint_flip_map [] with INPUT.RANDOM_FLIP "none" ({chiral})'}
    names = layout.keypoint_names
    pairs = ", ".join(f'("{names[k]}", "{names[j]}")' for k, j in enumerate(layout.flip_idx) if k < j)
    return {"yolo_flip": "flip_idx: the keypoints that a mirror symmetry of the target (shape and materials) swaps, "
                         "so a left-right flip relabels what it shows",
            "coco_flip": f"keypoint_flip_map [{pairs}] (a mirror symmetry of the target's shape and materials; "
                         "empty: every keypoint on its plane), INPUT.RANDOM_FLIP may stay on"}


def _command_texts(layout, folder: str, has_val: bool) -> dict[str, str]:
    """The paths the README's commands name, quoted as each command reads them (a shell word: shlex; a Python
    string: repr), so a folder with a space or a quote still pastes and runs; the COCO snippet opens the
    validation file only where the export wrote one."""
    name, seq = os.path.basename(folder), layout.sequence
    coco = os.path.join(folder, "annotations", f"keypoints_{'val' if has_val else 'train'}.json")
    return {"parent_sh": shlex.quote(os.path.dirname(folder)), "name_sh": shlex.quote(name),
            "keypoints_sh": shlex.quote(f"{name}/models/keypoints.mat"),
            "seq_json_sh": shlex.quote(os.path.join(folder, seq, f"{seq}.json")),
            "seq_synthetic_sh": shlex.quote(os.path.join(folder, seq, "synthetic") + "/"),
            "yolo_data_sh": shlex.quote(f"data={os.path.join(folder, 'data.yaml')}"),
            "coco_gt_py": repr(coco), "coco_name_py": repr(f"{name}_train"),
            "coco_train_py": repr(os.path.join(folder, "annotations", "keypoints_train.json")),
            "coco_images_py": repr(os.path.join(folder, "images")),
            "bop_gt_py": repr(os.path.join(folder, "train_pbr", "000000", "scene_gt.json")),
            "bop_ply_py": repr(os.path.join(folder, "models_eval", "obj_000001.ply"))}


def readme_text(layout, K: np.ndarray, n: int, pitch_m: float, manifest: dict, folder: str, masks: bool = True,
                has_val: bool = True) -> str:
    """The folder's README: where it came from, the common conventions, the format's layout and the command its
    tool runs on it. folder: the export folder's absolute path (as exported); masks: the dataset has masks (the
    boxes' source); has_val: the export has a validation split (COCO's keypoints_val.json)."""
    head = (f"# {layout.target}: {layout.fmt} export of an envisat-pose dataset\n\n"
            f"Made by `envisat dataset export` from a {layout.mode}-mode dataset (root seed "
            f"{manifest.get('root_seed')}, {manifest.get('num_images')} images, {n} px). `export.json` records "
            "the export's settings and image counts.\n\n")
    common = _COMMON.format(k=len(layout.keypoint_names), names=", ".join(layout.keypoint_names),
                            f=float(K[0, 0]), cx=float(K[0, 2]), cy=float(K[1, 2]), n=n)
    body = _FORMAT[layout.fmt] + (_SPNV2_RUN[layout.mode] if layout.fmt == "speedplus" else "")
    body = body.format(pitch=pitch_m, folder=folder, parent=os.path.dirname(folder), name=os.path.basename(folder),
                       seq=layout.sequence, k=len(layout.keypoint_names), n=n, sigma=OKS_SIGMA,
                       **_flip_texts(layout), **_symmetry_texts(layout), **_box_texts(masks),
                       **_command_texts(layout, folder, has_val))
    return head + common + "\n" + body
