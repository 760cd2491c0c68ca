"""`envisat dataset inspect` as one call: a generated dataset's statistics (datagen.dataset.dataset_stats), a
montage of its first images with their labels drawn and, optionally, those samples as a Rerun recording."""

from __future__ import annotations

import contextlib
import os
import warnings

from envisat_pose.config import InputError, path_arg, rrd_arg
from envisat_pose.datagen.appearance import takes_class_appearance
from envisat_pose.datagen.render_view import target_mask_values
from envisat_pose.dataset_target import check_dataset_target_file
from envisat_pose.out_dirs import check_out_file, make_out_file_dir
from envisat_pose.out_lock import output_lock
from envisat_pose.png_marks import JOB_KEY, written_png
from envisat_pose.shard_reader import checked_shards, load_dataset_manifest, unfinished_dataset
from envisat_pose.target import DEFAULT_TARGET, load_target

MONTAGE_NAME = "montage.png"  # the montage's default name, in the dataset's folder
JOB = "dataset inspect"  # the job its montage's PNG mark names (png_marks): a rerun's to replace
OUTPUT_KEYS = ("montage", "montage_images", "rrd")  # what inspect_dataset adds to the statistics


def inspect_dataset(src: str, montage: str | None = None, count: int = 16, rrd: str | None = None,
                    skip_damaged: bool = False, target: str | None = None) -> dict:
    """The statistics of the dataset folder `src` (returned; with `unfinished_dataset` and a warning where its
    generate job has shards still to write, `skipped_damaged_shards` where skip_damaged left some out), a montage
    of its first `count` images at `montage` (None: src/montage.png) and, with `rrd`, those samples as a Rerun
    recording (a .rrd path), its target drawn from the file its manifest records (or `target`, that file given
    from here: its sha256 must be the recorded one). Every input and output path is checked before any is
    written. The returned dict also holds `montage` (its path), `montage_images` (how many it drew) and `rrd`
    (the path or None)."""
    src = path_arg(src, "src")
    default = montage is None  # a path the user named is theirs to have replaced; the default is checked below
    montage = os.path.join(src, MONTAGE_NAME) if default else path_arg(montage, "montage")
    rrd = rrd_arg(rrd)
    target = path_arg(target, "target") if target is not None else None
    if type(count) is not int or count < 1:
        raise InputError(f"count {count!r}: expected at least 1 image in the montage")
    check_out_file(montage, "montage")
    if default and os.path.lexists(montage) and not written_png(montage, JOB):
        raise InputError(f"montage {montage!r} (the default) holds a file no `envisat {JOB}` wrote (no {JOB_KEY!r} "
                         "mark naming it): not the job's to replace; give another `montage` path, or move it")
    if rrd is not None:
        check_out_file(rrd, "rrd")
    from envisat_pose.datagen.dataset import dataset_stats
    from envisat_pose.datagen.dataset import montage as write_montage

    manifest = load_dataset_manifest(src, "src")
    if rrd is not None:  # the recording draws the target: its file found and unchanged, before any output
        check_dataset_target_file(src, manifest, target)
    shards, skipped = checked_shards(src, skip_damaged, "src")
    stats = dataset_stats(shards)
    unfinished = unfinished_dataset(manifest)
    if unfinished:
        stats["unfinished_dataset"] = f"{unfinished}: these statistics cover the shards written so far"
        warnings.warn(f"dataset {src!r}: {unfinished}: rerun its `envisat generate` command to finish it",
                      stacklevel=2)
    if skipped:
        stats["skipped_damaged_shards"] = skipped
    with contextlib.ExitStack() as locks:  # one job at a time on each output file (out_lock)
        for path, field in ((montage, "montage"), (rrd, "rrd")):
            if path is not None:
                locks.enter_context(output_lock(path, "dataset inspect", field=field, folder=False))
        make_out_file_dir(montage, "montage")
        drawn = write_montage(shards, montage, count=count, job=JOB)
        if rrd is not None:
            make_out_file_dir(rrd, "rrd")
            write_samples_rrd(shards, rrd, count, *recorded_target(manifest, target))
    return stats | dict(zip(OUTPUT_KEYS, (montage, drawn, rrd)))


def recorded_target(manifest: dict, given: str | None = None) -> tuple:
    """(the dataset's Target: the file its manifest records (given: that file from here), ENVISAT for a dataset
    written before targets; the
    {geom name: mask value} its masks hold, datagen.render_view.target_mask_values, or None where they are the
    factory's classes)."""
    target = load_target(given or (manifest.get("target") or {}).get("file", DEFAULT_TARGET), "target")
    return target, None if takes_class_appearance(g.name for g in target.geoms) else target_mask_values(target)


def write_samples_rrd(source: str | list[str], path: str, count: int, target=None,
                      mask_values: dict | None = None) -> None:
    """The first `count` samples as a Rerun recording (analysis.recording.write_samples_recording), read lazily.
    source: a dataset folder or its checked shard files; target, mask_values: the dataset's (recorded_target;
    None: ENVISAT's)."""
    from envisat_pose.analysis.recording import Sample, write_samples_recording
    from envisat_pose.datagen.dataset import iter_samples, sample_png
    from envisat_pose.datagen.shards import decode_png

    samples = (Sample(key, sample_png(members, label), label,
                      mask=decode_png(members["mask.png"]) if "mask.png" in members else None,
                      depth_png=members.get("depth.png"))
               for key, label, members in iter_samples(source, limit=count))
    write_samples_recording(path, samples, target, mask_values)
