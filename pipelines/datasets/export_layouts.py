"""The folder layouts of `envisat dataset export` (docs/formats.md): for each format, the files written once
(`static_files`), what one sample writes and records (`write_sample`, in a worker), and the annotation files
assembled from the records in sample order (`assemble`, streamed: memory flat in the dataset's size).

A sample's record is one JSON line; a worker writes its shard's lines to `.records/NNNNNN.jsonl` in the staging
folder, and the assembly reads them back shard by shard.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from envisat_pose.datagen import export_formats as fx

RECORDS = ".records"
BOP_SCENE_SIZE = 1000  # images per BOP scene in random mode (BOP's own PBR scenes hold 1000)


@dataclass(frozen=True)
class Layout:
    """What every sample of one export shares (plain data: it travels to the workers).

    fmt: one of export_formats.FORMATS; ext: 'png' or 'jpg'; mode: the dataset's 'random' or 'sequence';
    sequence: the sequence folder's name (speedplus, sequence mode); target: the target's name;
    keypoint_names: (K,); keypoints_T_m: (K, 3) list; outline_T_m: (V, 3) list, the model's vertices (bop, coco,
    yolo-pose); outline_faces: (F, 3) list, its triangles (bop: the silhouette beyond the image);
    depth_scale_mm: mm per depth unit, None when the dataset has no depth; skeleton: (E, 2) list of 0-based
    keypoint index pairs joined along the target's edges (Target.skeleton); flip_idx: (K,) the keypoints'
    permutation under a left-right flip of the image (Target.mirror_perm), None for a chiral target; symmetric:
    rotations of the target look the same in an image (BOP's symmetries_discrete).
    """

    fmt: str
    ext: str
    mode: str
    sequence: str
    target: str
    keypoint_names: tuple[str, ...]
    keypoints_T_m: list
    outline_T_m: list
    depth_scale_mm: float | None
    skeleton: list
    flip_idx: list | None = None
    symmetric: bool = False
    outline_faces: list = ()


def image_name(layout: Layout, i: int, split: str) -> str:
    """The path of sample i's image inside the export folder."""
    if layout.fmt == "speedplus":
        root = layout.sequence if layout.mode == "sequence" else ""
        return os.path.join(root, "synthetic", "images", f"img{i:06d}.{layout.ext}")
    if layout.fmt == "bop":
        scene, im_id = bop_ids(layout, i)
        return os.path.join("train_pbr", f"{scene:06d}", "rgb", f"{im_id:06d}.{layout.ext}")
    return os.path.join("images", split, f"{i:06d}.{layout.ext}")


def speedplus_mask_name(layout: Layout, i: int) -> str:
    """The path of sample i's mask (SPNv2's `masks/` beside `images/`, the image's stem, .png)."""
    images = os.path.dirname(image_name(layout, i, "train"))
    return os.path.join(os.path.dirname(images), "masks", f"img{i:06d}.png")


def bop_ids(layout: Layout, i: int) -> tuple[int, int]:
    """(scene id, image id) of sample i: a sequence is one scene; random views fill scenes of 1000."""
    return (0, i) if layout.mode == "sequence" else divmod(i, BOP_SCENE_SIZE)


def _write(stage: str, rel: str, data: bytes) -> None:
    path = os.path.join(stage, rel)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "wb") as fh:
        fh.write(data)


def write_sample(layout: Layout, stage: str, i: int, split: str, label: dict, image: bytes,
                 mask: np.ndarray | None, depth_png: bytes | None) -> dict:
    """Write sample i's files into the staging folder; return its record (what the annotation files need)."""
    name = image_name(layout, i, split)
    _write(stage, name, image)
    shape = mask.shape if mask is not None else None
    record: dict = {"i": i, "split": split}
    if layout.fmt == "speedplus":
        record["entry"] = fx.speedplus_entry(os.path.basename(name), label)
        record["t_s"] = label.get("scene", {}).get("t_s")
        if mask is not None:
            _write(stage, speedplus_mask_name(layout, i), _png((mask > 0).astype(np.uint8) * 255))
    elif layout.fmt == "coco":
        record.update(_coco_record(layout, name, i, label, mask))
    elif layout.fmt == "yolo-pose":
        h, w = shape or _label_size(label)
        box = _box(layout, label, mask)
        rows = fx.yolo_row(label, box, w, h) + "\n" if box is not None else ""
        _write(stage, os.path.join("labels", split, f"{i:06d}.txt"), rows.encode())
    else:
        scene, im_id = bop_ids(layout, i)
        folder = os.path.join("train_pbr", f"{scene:06d}")
        silhouette = _png((mask > 0).astype(np.uint8) * 255)
        for kind in ("mask", "mask_visib"):  # one object, no occluder: its whole silhouette is the visible one
            _write(stage, os.path.join(folder, kind, f"{im_id:06d}_000000.png"), silhouette)
        if depth_png is not None:
            _write(stage, os.path.join(folder, "depth", f"{im_id:06d}.png"), depth_png)
        record.update(scene=scene, im_id=im_id, gt=fx.bop_gt(label), camera=fx.bop_camera(label, layout.depth_scale_mm),
                      info=_bop_info(layout, label, mask))
    return record


def _bop_info(layout: Layout, label: dict, mask: np.ndarray) -> dict:
    """scene_gt_info's entry; the silhouette beyond the image is counted only where the model leaves it."""
    h, w = mask.shape
    outline = fx.project_points_px(np.asarray(layout.outline_T_m), label)
    box = fx.outline_box(outline, w, h, clip=False)
    inside = box is not None and box[0] >= 0 and box[1] >= 0 and box[2] < w and box[3] < h
    truncated = 0 if inside else fx.truncated_px_count(np.asarray(layout.outline_T_m), np.asarray(layout.outline_faces),
                                                        label, w, h)
    return fx.bop_gt_info(mask, outline, truncated)


def _png(image: np.ndarray) -> bytes:
    import cv2

    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return data.tobytes()


def _label_size(label: dict) -> tuple[int, int]:
    """(height, width) from the principal point (the factory's is the image centre)."""
    K = np.asarray(label["K"], dtype=float)
    return int(round(2 * K[1, 2] + 1)), int(round(2 * K[0, 2] + 1))


def _box(layout: Layout, label: dict, mask: np.ndarray | None) -> tuple[int, int, int, int] | None:
    """The target's box: the mask's, or without a mask the projected model's, clipped to the image."""
    if mask is not None:
        return fx.mask_box(mask)
    h, w = _label_size(label)
    return fx.outline_box(fx.project_points_px(np.asarray(layout.outline_T_m), label), w, h, clip=True)


def _coco_record(layout: Layout, name: str, i: int, label: dict, mask: np.ndarray | None) -> dict:
    h, w = mask.shape if mask is not None else _label_size(label)
    R, t = fx.pose_cam_from_target(label)
    image = {"id": i + 1, "file_name": os.path.relpath(name, "images"), "width": int(w), "height": int(h),
             "K": np.asarray(label["K"], dtype=float).tolist()}
    box = _box(layout, label, mask)
    if box is None:
        return {"image": image, "annotation": None}
    kps = fx.coco_keypoints(label)
    bbox = fx.coco_bbox(box)
    area = float(np.count_nonzero(mask)) if mask is not None else bbox[2] * bbox[3]
    ann = {"id": i + 1, "image_id": i + 1, "category_id": 1, "bbox": bbox, "area": area, "iscrowd": 0,
           "keypoints": kps, "num_keypoints": int(sum(1 for v in kps[2::3] if v > 0)),
           "pose": {"R_cam_from_target": R.tolist(), "q_cam_from_target_wxyz": fx.quat_wxyz(R),
                    "t_cam_from_target_m": t.tolist()}}
    return {"image": image, "annotation": ann}


# --- assembly (main process, after the workers) -----------------------------------------------------------------

def read_records(stage: str) -> Iterator[dict]:
    """Every record in sample order (the record files sort by shard index)."""
    folder = os.path.join(stage, RECORDS)
    for name in sorted(os.listdir(folder)):
        with open(os.path.join(folder, name), encoding="utf-8") as fh:
            for line in fh:
                yield json.loads(line)


def _write_array(path: str, items) -> int:
    """A JSON array written item by item; returns the count."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    n = 0
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("[")
        for item in items:
            fh.write(("," if n else "") + "\n" + json.dumps(item))
            n += 1
        fh.write("\n]\n")
    return n


def assemble(layout: Layout, stage: str, splits: tuple[str, ...]) -> dict[str, int]:
    """Write the annotation files from the records; returns the images per split."""
    if layout.fmt == "speedplus":
        return _assemble_speedplus(layout, stage)
    if layout.fmt == "coco":
        return {s: _assemble_coco(layout, stage, s) for s in splits}
    if layout.fmt == "bop":
        return {"train_pbr": _assemble_bop(stage)}
    return {s: sum(1 for r in read_records(stage) if r["split"] == s) for s in splits}


def _assemble_speedplus(layout: Layout, stage: str) -> dict[str, int]:
    if layout.mode == "sequence":
        seq = layout.sequence
        n = _write_array(os.path.join(stage, seq, f"{seq}.json"), (r["entry"] for r in read_records(stage)))
        # one time and one name per frame: small beside the images
        meta = {"sequence": seq, "frames": n, "t_s": [r["t_s"] for r in read_records(stage)],
                "filenames": [r["entry"]["filename"] for r in read_records(stage)]}
        with open(os.path.join(stage, seq, "metadata.json"), "w", encoding="utf-8") as fh:
            json.dump(meta, fh, indent=1)
        return {seq: n}
    names = {"train": "train.json", "val": "validation.json"}  # both, as SPEED+ has (one may be empty)
    return {s: _write_array(os.path.join(stage, "synthetic", names[s]),
                            (r["entry"] for r in read_records(stage) if r["split"] == s)) for s in names}


def _assemble_coco(layout: Layout, stage: str, split: str) -> int:
    path = os.path.join(stage, "annotations", f"keypoints_{split}.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)

    category = {"id": 1, "name": layout.target, "supercategory": "spacecraft",
                "keypoints": list(layout.keypoint_names), "skeleton": fx.coco_skeleton(layout.skeleton),
                "keypoints_3d_m": layout.keypoints_T_m}
    n = 0
    with open(path, "w", encoding="utf-8") as fh:
        fh.write('{"info": ' + json.dumps({"description": f"{layout.target} keypoints, envisat-pose export",
                                             "version": "1.0"}))
        fh.write(', "licenses": [], "images": [')
        for r in read_records(stage):
            if r["split"] == split:
                fh.write(("," if n else "") + "\n" + json.dumps(r["image"]))
                n += 1
        fh.write('\n], "annotations": [')
        k = 0
        for r in read_records(stage):
            if r["split"] == split and r["annotation"] is not None:
                fh.write(("," if k else "") + "\n" + json.dumps(r["annotation"]))
                k += 1
        fh.write('\n], "categories": [' + json.dumps(category) + "]}\n")
    return n


def _assemble_bop(stage: str) -> int:
    """scene_gt.json, scene_camera.json and scene_gt_info.json of each scene, keyed by image id."""
    files, scene, n = {}, None, 0

    def close():
        for fh in files.values():
            fh.write("\n}\n")
            fh.close()
        files.clear()

    try:
        for r in read_records(stage):
            if r["scene"] != scene:
                close()
                scene, first = r["scene"], True
                folder = os.path.join(stage, "train_pbr", f"{scene:06d}")
                os.makedirs(folder, exist_ok=True)
                for kind in ("scene_gt", "scene_camera", "scene_gt_info"):
                    files[kind] = open(os.path.join(folder, f"{kind}.json"), "w", encoding="utf-8")
                    files[kind].write("{")
            sep = "\n" if first else ",\n"
            first = False
            files["scene_gt"].write(f'{sep}"{r["im_id"]}": {json.dumps([r["gt"]])}')
            files["scene_camera"].write(f'{sep}"{r["im_id"]}": {json.dumps(r["camera"])}')
            files["scene_gt_info"].write(f'{sep}"{r["im_id"]}": {json.dumps([r["info"]])}')
            n += 1
    finally:
        close()
    return n
