"""`envisat dataset export`: a generated dataset (random or sequence mode, any resolution) into a folder of a
format the field trains on: SPEED+, COCO keypoints, BOP or YOLO-pose (docs/formats.md states every convention).

The shards are checked against the manifest first (a damaged one stops the export in one line, or is left out
with skip_damaged). One task per shard, on the local process pool, converts its samples: images (the PNG bytes
of the shard unchanged, or JPEG on request; BOP's always three-channel JPEG), masks, depth, and a record per
sample. The annotation files are then assembled from the records, streamed. Everything is written into a hidden
staging folder beside `out_dir`, renamed to `out_dir` only when complete (an existing empty `out_dir`, such as
the working folder, gets its entries): an error or an interrupt leaves nothing behind, and an existing non-empty
`out_dir` is refused. Files that name the folder (YOLO-pose's data.yaml, the README's commands) name `out_dir`'s
absolute path, never the staging folder's.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import tempfile
from dataclasses import asdict, dataclass

import numpy as np

from envisat_pose.config import Config, InputError, check, config_arg, path_arg
from envisat_pose.datagen import export_formats as fx
from envisat_pose.datagen.generate_config import config_from_json
from envisat_pose.dataset_target import check_dataset_target_file
from envisat_pose.geometry import load_camera
from envisat_pose.io import stage_prefix, sweep_stale_stages, usual_mode
from envisat_pose.out_dirs import check_out_dir, refuse_overlap
from envisat_pose.out_lock import is_lock_file, locks_output
from envisat_pose.pipelines.common.threads import compute_threads
from envisat_pose.pipelines.datasets import export_layouts as lay
from envisat_pose.pipelines.datasets.export_readme import readme_text
from envisat_pose.pools import RunnerConfig, run_tasks, thread_env, warn_oversubscribed
from envisat_pose.provenance import dataset_ref
from envisat_pose.shard_reader import (
    checked_shards,
    load_dataset_manifest,
    read_shard,
    skip_hint,
    unfinished_dataset,
)
from envisat_pose.target import APPENDAGE_GROUP, load_target
from envisat_pose.target_mesh import ply_bytes

STAGE_PREFIX = ".tmp-export-"


@dataclass(frozen=True)
class ExportConfig(Config):
    """fmt: speedplus | coco | bop | yolo-pose. image_format: png (the shards' bytes) or jpg (quality 95); bop
    ignores it (its train_pbr images are always JPEG, as the BOP toolkit expects).
    val_fraction: share of the images in the validation split (None: 0.2 for random views, 0 for a sequence,
    whose split is its last frames); seed: the split's seed. target: the target's MJCF file where the dataset's
    recorded one (its config's `target`) is not found from here; None: the recorded one. Either way its sha256
    must be the one the manifest recorded."""

    fmt: str
    image_format: str = "png"
    val_fraction: float | None = None
    seed: int = 0
    target: str | None = None

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check(self.fmt in fx.FORMATS, f"{p}fmt", self.fmt, " | ".join(fx.FORMATS))
        check(self.image_format in ("png", "jpg"), f"{p}image_format", self.image_format, "png or jpg")
        vf = self.val_fraction
        check(vf is None or 0.0 <= vf < 1.0, f"{p}val_fraction", vf, "a fraction in [0, 1)")
        check(isinstance(self.seed, int) and 0 <= self.seed < 2**63, f"{p}seed", self.seed,
              "a non-negative integer seed below 2^63")


@dataclass(frozen=True)
class ExportSummary:
    """out_dir: the folder written; images: per split (or sequence / scene set); skipped: damaged shards left out."""

    out_dir: str
    fmt: str
    images: dict
    skipped: list


@locks_output("out_dir", "dataset export", beside=True)  # the folder appears whole, by a rename (_publish)
def export_dataset(src: str, out_dir: str, cfg: ExportConfig, *, workers: int = 1, skip_damaged: bool = False,
                   progress: bool = False, on_shard=None) -> ExportSummary:
    """Export the dataset folder `src` into the new folder `out_dir` in cfg's format (module docstring). Returns an
    ExportSummary: out_dir (the folder written), fmt, images (how many per split, sequence or scene set) and
    skipped (the damaged shards left out with skip_damaged). on_shard(count): called after each shard (a progress
    hook). InputError for a bad argument, a missing or damaged dataset (naming the shard) or an `out_dir` that
    exists and holds anything or lies inside `src`."""
    cfg, src, out_dir = config_arg(cfg, ExportConfig), path_arg(src, "src"), path_arg(out_dir, "out_dir")
    check(type(workers) is int and workers >= 1, "workers", workers, "at least 1 worker process (an integer)")
    check_out_dir(out_dir, field="out_dir")
    refuse_overlap(out_dir, src, "out_dir", "src")  # an export inside the dataset: files among its shards
    if os.path.isdir(out_dir) and _entries(out_dir):
        raise InputError(f"out_dir {out_dir!r} exists and is not empty: an export writes a new folder")
    manifest = load_dataset_manifest(src, "src")
    unfinished = unfinished_dataset(manifest)
    if unfinished:
        raise InputError(f"src {src!r}: {unfinished}: rerun its `envisat generate` command to finish it")
    with skip_hint():
        shards, skipped = checked_shards(src, skip_damaged, "src")
    warn_oversubscribed(workers, units=len(shards))  # one process a shard at most
    gen = _generate_config(src, manifest, cfg.target)
    layout = _layout(cfg, gen, src, manifest)
    final_dir = os.path.abspath(out_dir)  # what the staging folder becomes: the path data.yaml and README name
    if cfg.fmt == "bop" and not gen.write_mask:
        raise InputError(f"src {src!r}: bop needs the dataset's masks (it was generated with write_mask = false)")
    if cfg.fmt == "speedplus" and layout.mode == "sequence" and cfg.val_fraction:
        raise InputError(f"val_fraction {cfg.val_fraction}: a sequence exports as one SHIRT-style sequence "
                         "folder, not split")
    if cfg.fmt == "bop" and cfg.val_fraction:  # it wrote every image to train_pbr without a word
        raise InputError(f"val_fraction {cfg.val_fraction}: bop exports one split, train_pbr (BOP's synthetic "
                         "training images); leave it out, or export another format for a validation split")
    counts = _shard_counts(manifest, shards)
    splits = _split_flags(sum(counts), cfg, layout.mode)
    stage, made = _make_stage(out_dir)
    moved: list[str] = []  # an existing empty out_dir: the entries moved into it so far
    try:
        _write_static(layout, stage, gen, manifest, bool(splits.any()), final_dir)
        _run_shards(layout, stage, shards, counts, splits, workers, progress, on_shard)
        images = lay.assemble(layout, stage, ("train", "val") if splits.any() else ("train",))
        shutil.rmtree(os.path.join(stage, lay.RECORDS))
        _write_json(os.path.join(stage, "export.json"), {
            "format": cfg.fmt, "config": asdict(cfg), "source": dataset_ref(src),
            "source_manifest_root_seed": manifest.get("root_seed"), "images": images, "skipped_damaged_shards": skipped,
            "target": load_target(gen.target).record(gen.target), "keypoint_names": list(layout.keypoint_names),
            "image_ext": layout.ext,
            "box_source": _box_source(cfg.fmt, gen.write_mask)})
        _publish(stage, out_dir, moved)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        for name in moved:  # an existing out_dir is left empty, as it was
            _remove(os.path.join(out_dir, name))
        for folder in made:
            with contextlib.suppress(OSError):
                os.rmdir(folder)
        raise
    return ExportSummary(out_dir, cfg.fmt, images, skipped)


def _publish(stage: str, out_dir: str, moved: list[str]) -> None:
    """The staging folder becomes out_dir: renamed to it, or, where out_dir exists (empty: checked before), its
    entries moved into it (the folder stays: the working folder `.`, a mount point), each name added to `moved`
    before it moves (what a failure removes again). InputError when out_dir refuses them, or when another job
    (a second export to the same --out) has filled out_dir meanwhile: nothing of it is touched or merged."""
    busy = f"out_dir {out_dir!r} was filled by another job while this export ran; nothing was written (use another " \
        "folder)"
    try:
        if not os.path.isdir(out_dir):
            os.rename(stage, out_dir)  # fails (not empty) where another job's folder took the name meanwhile
            return
        if _entries(out_dir):
            raise InputError(busy)
        for name in sorted(os.listdir(stage)):
            if os.path.lexists(os.path.join(out_dir, name)):
                raise InputError(busy)
            moved.append(name)
            shutil.move(os.path.join(stage, name), os.path.join(out_dir, name))
        os.rmdir(stage)
    except OSError as err:
        if os.path.isdir(out_dir) and sorted(_entries(out_dir)) != sorted(moved):
            raise InputError(busy) from None
        raise InputError(f"out_dir {out_dir!r}: cannot move the export into it ({err.strerror or err})") from None


def _entries(folder: str) -> list[str]:
    """What folder holds besides the lock file (out_lock: this export's own, or a killed job's)."""
    return [name for name in os.listdir(folder) if not is_lock_file(name)]


def _remove(path: str) -> None:
    if os.path.isdir(path) and not os.path.islink(path):
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(OSError):
            os.remove(path)


def _generate_config(src: str, manifest: dict, target: str | None = None):
    """The dataset's generate config, its target file the one given in its place (the recorded path may no longer
    be there), that file checked first (_check_target_file: the config's sizes follow its target)."""
    check_dataset_target_file(src, manifest, target)
    try:
        recorded = dict(manifest["config"])
        if target is not None:
            recorded["target"] = target
        return config_from_json(json.dumps(recorded))
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(f"src {src!r}: manifest.json holds no readable generate config ({err})") from None


def _layout(cfg: ExportConfig, gen, src: str, manifest: dict) -> lay.Layout:
    """What every sample shares: the target's keypoints, skeleton and model outline from its MJCF, the sequence's
    name, the images' extension (BOP's train_pbr: always jpg, the toolkit's extension for PBR splits)."""

    target = _dataset_target(src, gen, manifest)
    mesh = target.mesh(gen.appendages_on) if cfg.fmt in ("bop", "coco", "yolo-pose") else None
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", os.path.basename(os.path.normpath(os.path.abspath(src)))) or "sequence"
    depth_mm = gen.depth_scale_m * 1000.0 if gen.write_depth else None
    names, points = target.keypoint_names, target.keypoints_T_m.tolist()
    mirror = target.mirror_perm if _shape_checked(target, gen.appendages_on) else None
    return lay.Layout(fmt=cfg.fmt, ext="jpg" if cfg.fmt == "bop" else cfg.image_format, mode=gen.mode,
                      sequence=name, target=target.name, keypoint_names=names, keypoints_T_m=points,
                      outline_T_m=mesh.vertices_T_m.tolist() if mesh is not None else [], depth_scale_mm=depth_mm,
                      skeleton=[[int(a), int(b)] for a, b in target.skeleton],
                      flip_idx=None if mirror is None else list(mirror),
                      symmetric=bool(_bop_symmetries(target, gen.appendages_on)),
                      outline_faces=mesh.faces.tolist() if cfg.fmt == "bop" else [])


def _dataset_target(src: str, gen, manifest: dict):
    """The dataset's target (its config's `target` file; datasets written before it: ENVISAT), refused when the
    file's sha256 differs from the one its manifest recorded."""

    target = load_target(gen.target, "target")
    recorded = (manifest.get("target") or {}).get("sha256")
    if recorded is not None and recorded != target.sha256:
        raise InputError(f"src {src!r}: its target file {gen.target!r} changed since the dataset was generated "
                         f"(sha256 {target.sha256[:12]}..., the manifest recorded {recorded[:12]}...)")
    return target


def _box_source(fmt: str, masks: bool) -> str | None:
    """What export.json says the boxes came from: the mask, or without masks (COCO, YOLO-pose) the projected
    model (export_layouts._box); None where the format writes no box (SPEED+)."""
    if fmt == "speedplus":
        return None
    return "mask" if masks else "projected_model"


def _shard_counts(manifest: dict, shards: list[str]) -> list[int]:
    counts = {e["name"]: int(e["count"]) for e in manifest["shards"]}
    return [counts.get(os.path.basename(p), 0) for p in shards]


def _split_flags(n: int, cfg: ExportConfig, mode: str) -> np.ndarray:
    """(n,) bool, True for validation: a seeded random share of random views; a sequence's last frames.
    InputError when a val_fraction asked for (BOP's one split aside) leaves either split without an image."""
    vf = cfg.val_fraction if cfg.val_fraction is not None else (0.2 if mode == "random" else 0.0)
    n_val = int(round(vf * n))
    if cfg.val_fraction and cfg.fmt != "bop" and not 0 < n_val < n:
        empty = "training" if n_val else "validation"
        raise InputError(f"val_fraction {vf:g}: {n_val} of the {n} images in the validation split leaves the "
                         f"{empty} split empty; expected a fraction that leaves each split an image (or 0: no "
                         "validation split)")
    flags = np.zeros(n, dtype=bool)
    if n_val == 0:
        return flags
    if mode == "sequence":
        flags[n - n_val:] = True
    else:
        flags[np.random.default_rng(cfg.seed).permutation(n)[:n_val]] = True
    return flags


def _make_stage(out_dir: str) -> tuple[str, list[str]]:
    """A hidden staging folder beside out_dir (same file system: one rename at the end) and the parent folders
    made for it (removed again when the export fails)."""
    parent = os.path.dirname(os.path.abspath(out_dir))
    made, here = [], parent
    while not os.path.isdir(here):
        made.append(here)
        here = os.path.dirname(here)
    try:
        os.makedirs(parent, exist_ok=True)
        sweep_stale_stages(parent, STAGE_PREFIX)  # a killed export's (SIGKILL: no clean-up ran)
        stage = tempfile.mkdtemp(prefix=stage_prefix(STAGE_PREFIX) + os.path.basename(os.path.abspath(out_dir)) + "-",
                                 dir=parent)
        os.chmod(stage, usual_mode(folder=True))  # mkdtemp's 0700 would become --out's: others could not read it
    except OSError as err:
        raise InputError(f"out_dir {out_dir!r}: cannot write there ({err.strerror or err})") from None
    return stage, made


def _write_json(path: str, data) -> None:
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=1)
        fh.write("\n")


def _pixel_pitch_m(gen) -> float:
    return gen.corruption.sensor.pixel_pitch_m_1024 * 1024.0 / gen.resolution_px


def _write_static(layout: lay.Layout, stage: str, gen, manifest: dict, has_val: bool, final_dir: str) -> None:
    """The files an export writes once: camera, model, keypoints, data.yaml, the folder's README. final_dir: the
    absolute path the staging folder `stage` is renamed to (data.yaml's `path`, the README's commands)."""

    n = gen.resolution_px
    K = load_camera().scaled(n, n).K
    if layout.fmt == "speedplus":
        from scipy.io import savemat

        _write_json(os.path.join(stage, "camera.json"), fx.speedplus_camera(K, n, n, _pixel_pitch_m(gen)))
        os.makedirs(os.path.join(stage, "models"), exist_ok=True)
        savemat(os.path.join(stage, "models", "keypoints.mat"),
                {"tango3Dpoints": np.asarray(layout.keypoints_T_m).T})
    elif layout.fmt == "bop":
        _write_bop_model(layout, stage, gen, K)
    elif layout.fmt == "yolo-pose":
        with open(os.path.join(stage, "data.yaml"), "w", encoding="utf-8") as fh:
            fh.write(yolo_yaml_text(layout, has_val, final_dir))
    with open(os.path.join(stage, "README.md"), "w", encoding="utf-8") as fh:
        fh.write(readme_text(layout, K, n, _pixel_pitch_m(gen), manifest, final_dir, gen.write_mask, has_val))


def _shape_checked(target, appendages: bool) -> bool:
    """Whether the images show the surface the target's symmetries and mirror were checked on (Target.mesh()):
    not where the dataset drew geoms of the appendages' group too."""
    return not (appendages and any(g.group == APPENDAGE_GROUP for g in target.geoms))


def _bop_symmetries(target, appendages: bool) -> dict:
    """models_info's symmetries_discrete: each rotation of the target that nothing in an image tells from the
    identity (Target.symmetries whose shape and materials keep it: the CubeSat's half-turns; none of ENVISAT's,
    which its array and materials break) as a row-major 4 x 4 in mm about the model's origin, the CoM. Nothing
    where the images show more than the symmetries were checked on (_shape_checked)."""
    if not _shape_checked(target, appendages):
        return {}
    kept = [s.R_T for s in target.symmetries if not s.broken_by]
    if not kept:
        return {}
    return {"symmetries_discrete": [np.vstack([np.c_[R, np.zeros(3)], [0, 0, 0, 1]]).ravel().tolist()
                                    for R in kept]}


def _write_bop_model(layout: lay.Layout, stage: str, gen, K: np.ndarray) -> None:
    """models/ (the mesh, its info, the keypoints), models_eval/ (the same mesh with area-weighted vertex normals,
    its info) and camera.json."""
    target = load_target(gen.target)
    mesh = target.mesh(gen.appendages_on)
    vertices_mm = mesh.vertices_T_m * 1000.0
    info = {"1": {**fx.bop_model_info(vertices_mm), **_bop_symmetries(target, gen.appendages_on)}}
    folder = os.path.join(stage, "models")
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, "obj_000001.ply"), "wb") as fh:
        fh.write(ply_bytes(mesh, scale=1000.0))
    _write_json(os.path.join(folder, "models_info.json"), info)
    os.makedirs(os.path.join(stage, "models_eval"), exist_ok=True)
    with open(os.path.join(stage, "models_eval", "obj_000001.ply"), "wb") as fh:
        fh.write(fx.ply_with_normals(vertices_mm, mesh.faces, fx.vertex_normals(vertices_mm, mesh.faces)))
    _write_json(os.path.join(stage, "models_eval", "models_info.json"), info)
    _write_json(os.path.join(folder, "keypoints_3d.json"),
                {"1": {"names": list(layout.keypoint_names),
                       "points_mm": (np.asarray(layout.keypoints_T_m) * 1000.0).tolist()}})
    n = gen.resolution_px
    camera = {"cx": float(K[0, 2]), "cy": float(K[1, 2]), "fx": float(K[0, 0]), "fy": float(K[1, 1]),
              "width": n, "height": n}
    if layout.depth_scale_mm is not None:
        camera["depth_scale"] = layout.depth_scale_mm
    _write_json(os.path.join(stage, "camera.json"), camera)


def _yaml_str(text: str) -> str:
    """A YAML scalar that reads back as exactly `text` (JSON's double-quoted string is YAML's: no name becomes
    a boolean or a number, no path's ': ' or ' #' ends it)."""
    return json.dumps(text, ensure_ascii=False)


def _yolo_flip_line(flip_idx: list | None) -> str:
    if flip_idx is None:
        return ("# no flip_idx: the target is chiral, a mirrored image shows another object (Ultralytics then sets "
                "fliplr = 0)")
    return (f"flip_idx: [{', '.join(str(int(k)) for k in flip_idx)}]  # a mirror symmetry's keypoints: a "
            "left-right flipped image shows the target with these swapped (README.md)")


def yolo_yaml_text(layout: lay.Layout, has_val: bool, final_dir: str) -> str:
    """Ultralytics's data.yaml: `path` the export folder's absolute path (data.yaml works from any working
    folder), kpt_shape [K, 3], kpt_oks_sigmas (K times export_formats.OKS_SIGMA; Ultralytics otherwise scores with
    1/K), flip_idx where the target has a mirror symmetry (layout.flip_idx; a chiral target has none, and
    Ultralytics then turns its left-right flip off), the keypoint and class names."""
    k = len(layout.keypoint_names)
    val = "images/val" if has_val else "images/train  # no validation images (--val-fraction 0, or too few images)"
    sigmas = ", ".join(f"{fx.OKS_SIGMA:g}" for _ in range(k))
    return ("# Ultralytics YOLO-pose dataset (envisat-pose export; conventions in README.md)\n"
            f"path: {_yaml_str(final_dir)}  # this folder, absolute; moved? edit it (or delete it: recent "
            "Ultralytics releases then take data.yaml's folder)\n"
            f"train: images/train\nval: {val}\n"
            f"kpt_shape: [{k}, 3]\n"
            f"kpt_oks_sigmas: [{sigmas}]  # OKS sigma per keypoint: {fx.OKS_SIGMA:g} each (README.md)\n"
            f"{_yolo_flip_line(layout.flip_idx)}\n"
            f"kpt_names:\n  0: [{', '.join(_yaml_str(n) for n in layout.keypoint_names)}]\n"
            f"names:\n  0: {_yaml_str(layout.target)}\n")


def _run_shards(layout, stage, shards, counts, splits, workers, progress, on_shard) -> None:
    """One task per shard on the local pool; a progress bar over the images."""
    from tqdm import tqdm

    starts = np.concatenate([[0], np.cumsum(counts)]).astype(int)
    tasks = [(asdict(layout), path, stage, k, int(starts[k]), splits[starts[k]:starts[k + 1]].tolist())
             for k, path in enumerate(shards)]
    runner = RunnerConfig(backend="local", workers=min(workers, len(tasks)),
                          env=thread_env(workers, ("OMP_NUM_THREADS", "OPENCV_FOR_THREADS_NUM"), len(tasks)))
    with tqdm(total=int(starts[-1]), unit="img", desc="export", disable=not progress) as bar:
        for _, n in run_tasks(export_shard, tasks, runner):
            bar.update(n)
            if on_shard is not None:
                on_shard(n)


def export_shard(layout_dict: dict, path: str, stage: str, index: int, start: int, val_flags: list) -> int:
    """A worker's task: every sample of one shard into the staging folder, its records to .records/; returns the
    samples written. Sample k of the shard is the export's sample start + k."""
    with compute_threads(cv2_n=1):  # one thread a worker; a run in the calling process gives it back
        return _export_shard(layout_dict, path, stage, index, start, val_flags)


def _export_shard(layout_dict: dict, path: str, stage: str, index: int, start: int, val_flags: list) -> int:
    from envisat_pose.datagen.dataset import sample_image, sample_png
    from envisat_pose.datagen.shards import decode_png

    layout = lay.Layout(**{**layout_dict, "keypoint_names": tuple(layout_dict["keypoint_names"])})
    lines = []
    for k, (key, members) in enumerate(read_shard(path)):
        where = f"{os.path.basename(path)}:{key}"
        try:
            label = json.loads(members["json"])
        except (KeyError, ValueError) as err:
            raise InputError(f"{where}: no readable .json label ({err})") from None
        if layout.ext == "png":
            image = sample_png(members, label)
        else:
            gray = sample_image(members, label, where)
            image = jpeg_bytes(np.dstack([gray] * 3) if layout.fmt == "bop" and gray.ndim == 2 else gray)
        mask = decode_png(members["mask.png"]) if members.get("mask.png") else None
        split = "val" if val_flags[k] else "train"
        lines.append(json.dumps(lay.write_sample(layout, stage, start + k, split, label, image, mask,
                                                 members.get("depth.png") if layout.depth_scale_mm else None)))
    folder = os.path.join(stage, lay.RECORDS)
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, f"{index:06d}.jsonl"), "w", encoding="utf-8") as fh:
        fh.write("".join(line + "\n" for line in lines))
    return len(lines)


def jpeg_bytes(image: np.ndarray) -> bytes:
    """(H, W) or (H, W, 3) uint8 as a JPEG at export_formats.JPEG_QUALITY."""
    import cv2

    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, fx.JPEG_QUALITY])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return data.tobytes()
