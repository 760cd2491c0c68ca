"""Reading a generated dataset back: verification against the manifest, statistics, a labelled montage."""

from __future__ import annotations

import glob
import json
import os

import numpy as np

from envisat_pose.config import InputError
from envisat_pose.datagen.corrupt import apply_corruption
from envisat_pose.datagen.labels import label_points_noun
from envisat_pose.datagen.shards import SHARD_GLOB, decode_png, encode_png, shard_name
from envisat_pose.geometry import CORNER_NAMES, EDGES
from envisat_pose.io import atomic_path
from envisat_pose.png_marks import marked_png
from envisat_pose.resumable import manifest_path
from envisat_pose.shard_reader import checked_shards, load_dataset_manifest, read_shard, shard_problems


def verify_dataset(out_dir: str) -> list[str]:
    """Returns a list of str: the problems of a dataset, one line each; an empty list means it verified (every
    shard present and matching its manifest entry by the core's one shard check, shard_reader.shard_problem:
    size, sha256, samples; and no shard-*.tar there that the manifest does not list). A manifest there that is
    unreadable or not a dataset's is its one problem: a damaged dataset. InputError when out_dir is no
    folder or holds no manifest: not a dataset."""
    out_dir = os.fspath(out_dir)
    try:
        manifest = load_dataset_manifest(out_dir)
    except InputError as err:
        if not os.path.isfile(manifest_path(out_dir)):
            raise
        return [str(err).removeprefix(f"dataset {out_dir!r}: ")]
    found = {}  # shard name: its problem
    listed = {e["name"]: e for e in manifest["shards"]}
    names = [shard_name(idx) for idx in range(int(manifest.get("num_shards", len(listed))))]
    for name in names:
        if name not in listed:
            what = "not finished" if os.path.exists(os.path.join(out_dir, name)) else "missing"
            found[name] = f"{name}: {what} (not in the manifest)"
    entries = [listed[n] for n in names if n in listed]
    for entry, issue in zip(entries, shard_problems(out_dir, entries)):
        if issue:
            found[entry["name"]] = f"{entry['name']}: {issue}"
    problems = [found[n] for n in names if n in found]
    for path in sorted(glob.glob(os.path.join(glob.escape(out_dir), SHARD_GLOB))):
        name = os.path.basename(path)
        if name not in listed and name not in names:  # beyond num_shards: another run's, or a copied-in file
            problems.append(f"{name}: not part of the dataset (the manifest does not list it; a `shard-*.tar` "
                            "glob would read it)")
    for tmp in sorted(glob.glob(os.path.join(glob.escape(out_dir), ".tmp-*"))):
        problems.append(f"{os.path.basename(tmp)}: partial file of an interrupted run")
    total = sum(e.get("count", 0) for e in manifest["shards"])
    if not manifest.get("complete") and not problems:
        problems.append("manifest marked incomplete")
    if manifest.get("complete") and total != manifest.get("num_images"):
        problems.append(f"{total} samples listed, expected {manifest.get('num_images')}")
    return problems


def dataset_shards(source: str | list[str]) -> list[str]:
    """The shard files of source: a dataset folder (its manifest's shards, checked against it: the core's
    checked_shards; a damaged one is one InputError; a str or a pathlib.Path) or a list of shard files already
    checked."""
    if isinstance(source, (str, os.PathLike)):
        source = os.fspath(source)
        load_dataset_manifest(source)
        return checked_shards(source, False, "dataset")[0]
    return [os.fspath(p) for p in source]


def iter_samples(source: str | list[str], limit: int | None = None):
    """(key, label dict, members) of a dataset's samples in shard order, at most `limit`. source: a dataset folder
    or its checked shard files (dataset_shards)."""
    n = 0
    for path in dataset_shards(source):
        for key, members in read_shard(path):
            where = f"{os.path.basename(path)}:{key}"
            try:
                label = json.loads(members["json"])
            except (KeyError, ValueError) as err:
                raise InputError(f"{where}: no readable .json label ({type(err).__name__}: {err})") from None
            if not members.get("png"):
                raise InputError(f"{where}: sample has no '.png' image member (members: {', '.join(sorted(members))})")
            yield key, label, members
            n += 1
            if limit is not None and n >= limit:
                return


def sample_image(members: dict[str, bytes], label: dict | None = None, where: str = "sample"):
    """A sample's image as training sees it: (H, W) uint8, corrupted. A sample stored clean (label
    image_stored = 'clean') gets its label's corruption applied here, deterministically: the same pixels
    (and, through sample_png, the same PNG bytes) as storage = 'corrupted' writes."""

    label = label if label is not None else json.loads(members["json"])
    if not members.get("png"):
        raise InputError(f"{where}: no '.png' image member (members: {', '.join(sorted(members))})")
    image = decode_png(members["png"])
    if image is None:
        raise InputError(f"{where}.png: not an image (cannot be decoded as PNG)")
    if label.get("image_stored") == "clean":
        image = apply_corruption(image, label["corruption"])
    return image


def sample_png(members: dict[str, bytes], label: dict | None = None) -> bytes:
    """The PNG bytes of a sample's corrupted image (corrupting a clean-stored one on read), byte-identical to
    the member a corrupted-storage dataset holds."""

    label = label if label is not None else json.loads(members["json"])
    if label.get("image_stored") != "clean":
        return members["png"]
    return encode_png(sample_image(members, label))


# ENVISAT's old names of the keypoint statistics, kept beside them for its datasets for one release (deprecated)
DEPRECATED_CORNER_KEYS = {"visible_corners_histogram": "visible_keypoints_histogram",
                          "in_frame_corners_mean": "in_frame_keypoints_mean"}


def dataset_stats(source: str | list[str]) -> dict:
    """Statistics over every label: counts, range, visible and in-frame keypoints (the histogram: K + 1 bins, 0 to
    the target's K keypoints), eclipses, corruption levels; keypoints_noun: what the labels call their points
    ("corners": ENVISAT's A-H, whose statistics also keep their deprecated corner-named keys, DEPRECATED_CORNER_KEYS;
    "keypoints": a target whose labels name them, labels.label_names_keypoints). source: a dataset folder or its
    checked shard files."""
    ranges, n_vis, n_frame, eclipse, earth, k = [], [], [], 0, 0, 0
    levels: dict[str, dict[str, int]] = {}
    nouns = set()
    for _, lab, _ in iter_samples(source):
        ranges.append(float(np.linalg.norm(lab["t_cam_from_target_m"])))
        n_vis.append(int(np.sum(lab["visible"])))
        k = max(k, len(lab["visible"]))
        n_frame.append(int(np.sum(lab["in_frame"])))
        nouns.add(label_points_noun(lab))
        scene = lab.get("scene", {})
        eclipse += bool(scene.get("eclipse"))
        earth += bool(scene.get("earth_backdrop"))
        if scene.get("appendages"):
            levels.setdefault("appendages", {}).setdefault("on", 0)
            levels["appendages"]["on"] += 1
        for kind, level in lab["corruption"].get("levels", {"model": lab["corruption"].get("model")}).items():
            levels.setdefault(kind, {}).setdefault(level, 0)
            levels[kind][level] += 1
    n = len(ranges)
    if n == 0:
        return {"samples": 0}
    r = np.array(ranges)
    points = {"keypoints_noun": "keypoints" if "keypoints" in nouns else "corners",
              "visible_keypoints_histogram": np.bincount(n_vis, minlength=k + 1).tolist(),
              "in_frame_keypoints_mean": float(np.mean(n_frame))}
    if points["keypoints_noun"] == "corners":
        points |= {old: points[new] for old, new in DEPRECATED_CORNER_KEYS.items()}
    return {
        "samples": n,
        "range_m": {"min": float(r.min()), "mean": float(r.mean()), "max": float(r.max())},
        **points,
        "eclipse_fraction": eclipse / n,
        "earth_backdrop_fraction": earth / n,
        "corruption_levels": {k: dict(sorted((str(a), b) for a, b in v.items())) for k, v in sorted(levels.items())},
    }


def draw_labels(gray_u8: np.ndarray, label: dict) -> np.ndarray:
    """A BGR copy of an image with the labelled box edges and corners (green visible, red hidden) and letters;
    another target's label: its keypoints and their names."""
    import cv2

    img = cv2.cvtColor(gray_u8, cv2.COLOR_GRAY2BGR)
    n = gray_u8.shape[0]
    scale = 16  # cv2 draws with 4 fractional bits: sub-pixel positions
    envisat = "corners_px" in label  # another target: its named keypoints, no box edges
    names = CORNER_NAMES if envisat else label["keypoint_names"]
    pts = [(int(round(u * scale)), int(round(v * scale))) for u, v in label["corners_px" if envisat else "keypoints_px"]]
    thick = max(1, n // 512)
    for a, b in EDGES if envisat else ():
        if label["in_frame"][a] or label["in_frame"][b]:
            cv2.line(img, pts[a], pts[b], (255, 160, 0), thick, cv2.LINE_AA, shift=4)
    for i, (p, vis, inside) in enumerate(zip(pts, label["visible"], label["in_frame"])):
        if not inside:
            continue
        color = (0, 220, 0) if vis else (0, 0, 255)
        cv2.circle(img, p, max(3, n // 100) * scale, color, thick, cv2.LINE_AA, shift=4)
        cv2.putText(img, names[i], (p[0] // scale + 4, p[1] // scale - 4), cv2.FONT_HERSHEY_SIMPLEX,
                    max(0.35, n / 1400), color, thick, cv2.LINE_AA)
    return img


def montage(source: str | list[str], path: str, count: int = 16, tile_px: int = 256, job: str | None = None) -> int:
    """Write a grid of the first `count` images with their labels drawn; returns how many were drawn. source: a
    dataset folder or its checked shard files; job: the job a .png's mark names (png_marks), else none."""
    import cv2

    if count < 1:
        raise InputError(f"count {count}: expected at least 1 image in the montage")
    path = os.fspath(path)
    tiles = []
    for key, lab, members in iter_samples(source, limit=count):
        tile = draw_labels(sample_image(members, lab, f"sample {key}"), lab)
        tiles.append(cv2.resize(tile, (tile_px, tile_px), interpolation=cv2.INTER_AREA))
    if not tiles:
        raise InputError(f"no samples to draw in the montage (count {count})")
    cols = int(np.ceil(np.sqrt(len(tiles))))
    rows = int(np.ceil(len(tiles) / cols))
    grid = np.zeros((rows * tile_px, cols * tile_px, 3), dtype=np.uint8)
    for k, tile in enumerate(tiles):
        r, c = divmod(k, cols)
        grid[r * tile_px : (r + 1) * tile_px, c * tile_px : (c + 1) * tile_px] = tile
    write_image(path, grid, job)
    return len(tiles)


def write_image(path: str, image: np.ndarray, job: str | None = None) -> None:
    """Encode an image by the path's extension (.png when none) and write it atomically (a temp file in the
    same folder, then a rename: a killed run never leaves a partial file). InputError when that fails. job: a
    PNG's mark (png_marks.marked_png: the job's next run knows the file for its own)."""
    import cv2

    ext = os.path.splitext(path)[1] or ".png"
    try:
        ok, data = cv2.imencode(ext, image)
    except cv2.error:
        ok = False
    if not ok:
        raise InputError(f"cannot encode the montage as {ext!r} for {path!r}: use .png or .jpg")
    data = data.tobytes()
    if job and ext.lower() == ".png":
        data = marked_png(data, job)
    try:
        with atomic_path(path, suffix=ext) as tmp:
            with open(tmp, "wb") as fh:
                fh.write(data)
    except OSError as err:
        raise InputError(f"cannot write the montage to {path!r} ({err.strerror or err})") from None
