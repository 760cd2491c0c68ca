"""The names and times of an image folder's frames (`envisat track`, `envisat adapt`; pipelines/runs/frames.py
opens the folder):

- names sorted naturally (runs of digits compared as numbers: frame_2 before frame_10); two files of one frame
  number (frame_01.png and frame_1.png, or img_7.png and img_7.jpg: the same frame saved twice) are refused,
  their order being unknown;
- numbered names that skip numbers under a frame rate cautioned against (`rate_hz` times frame k at k / rate_hz s
  by its position: the frames after a gap would be early by the missing frames' time; frames.scan_source warns),
  and names ending in decimals of unequal length (t_12.5, t_12.25: natural order is not their time order);
- a timestamps CSV (columns file,t_s; a spreadsheet's byte-order mark and spaces around the header's names
  allowed) read, one time per image, increasing in name order by at least the physics' least step (MIN_FRAME_DT_S,
  1e-4 s), none beyond the recording's clock (MAX_TIME_S);
- frames too far apart for the tracker's cold start to gather its window warned of (spacing_caution).
"""

from __future__ import annotations

import csv
import ntpath
import os
import re

import numpy as np

from envisat_pose.config import InputError

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".ppm", ".pnm", ".webp")  # OpenCV reads them
# image types a camera or a converter writes that the tracker does not read (OpenCV's wheel lacks them or needs a
# switch): their files among the frames are named, not passed over without a word
UNREAD_IMAGE_EXTENSIONS = (".gif", ".jp2", ".j2k", ".exr", ".hdr", ".pfm", ".heic", ".heif", ".avif", ".fits", ".fit",
                           ".fts", ".dng", ".cr2", ".nef", ".arw", ".raw", ".jxl")
MAX_TIME_S = (2 ** 63 - 1) / 1e9  # the largest frame time a recording's clock holds (Rerun's int64 ns), s
# the least interval between frames, s: tracker_bounds.MIN_FRAME_DT_S (the physics' and the filter's least step, the
# floor `rate_hz` keeps), held here as a number so that reading a folder's names imports no physics (a test keeps
# the two equal)
MIN_FRAME_DT_S = 1e-4
GAP_FACTOR = 1.5  # a step in the frame numbers this much over the usual one is a gap (not jitter in a clock's name)


def natural_key(name: str) -> tuple:
    """Sort key of a file name with its runs of digits compared as numbers (frame_2 < frame_10)."""
    parts = re.split(r"(\d+)", name)
    return tuple(int(p) if i % 2 else p for i, p in enumerate(parts))


def sorted_frames(folder: str, names: list[str]) -> list[str]:
    """The image files among names (hidden and dot files skipped), naturally sorted; InputError when two files
    have one frame number (their names without the extension compare equal: their order cannot be told), or when
    one is a link to nothing."""
    images = sorted((n for n in names if not n.startswith(".") and n.lower().endswith(IMAGE_EXTENSIONS)),
                    key=lambda n: (natural_key(n), n))
    for n in images:  # a link to a frame that is gone: skipped, the sequence silently lost that frame
        path = os.path.join(folder, n)
        if os.path.islink(path) and not os.path.exists(path):
            raise InputError(f"source {folder!r}: {n!r} is a link to {os.readlink(path)!r}, which does not exist; "
                             "expected an image file (restore the frame, or remove the link)")
    files = [n for n in images if os.path.isfile(os.path.join(folder, n))]
    seen: dict[tuple, str] = {}
    for n in files:
        key = natural_key(os.path.splitext(n)[0])
        if key in seen:
            raise InputError(f"source {folder!r}: {seen[key]!r} and {n!r} have the same frame number: their order is "
                             "ambiguous (expected one file per frame: remove a copy in another format, or rename them with "
                             "zero-padded numbers)")
        seen[key] = n
    return files


def unread_images(names: list[str]) -> list[str]:
    """The names among names (hidden files skipped) of image types the tracker does not read, naturally sorted."""
    return sorted((n for n in names if not n.startswith(".") and n.lower().endswith(UNREAD_IMAGE_EXTENSIONS)),
                  key=natural_key)


def unread_images_said(names: list[str]) -> str | None:
    """What to say of the files among names of image types the tracker does not read (unread_images): frames of
    the sequence saved as GIF, JPEG 2000, EXR, FITS or camera raw would otherwise be left out without a word; None
    when there are none."""
    unread = unread_images(names)
    if not unread:
        return None
    kinds = ", ".join(sorted({os.path.splitext(n)[1].lower() for n in unread}))
    shown = ", ".join(repr(n) for n in unread[:3]) + (f" and {len(unread) - 3} more" if len(unread) > 3 else "")
    return (f"{len(unread)} file(s) of an image type the tracker does not read ({kinds}: {shown}) are left out; if "
            "they are frames of the sequence, convert them to PNG, TIFF or JPEG")


def unread_images_caution(src: str, names: list[str]) -> str | None:
    """unread_images_said as a warning naming the folder src; None when there is nothing to say."""
    said = unread_images_said(names)
    return None if said is None else f"source {src!r}: {said}"


def numbering_gap(names: list[str]) -> tuple[str, str, int, int] | None:
    """(name, next name, their step, the usual step) for the first pair of names whose frame numbers step more than
    GAP_FACTOR times the usual (median) step, when the names are one pattern with one number that changes
    (img_0001.png, img_0002.png, ...); None otherwise."""
    parts = [re.fullmatch(r"(.*?)(\d+)(\D*)", os.path.splitext(n)[0]) for n in names]
    if len(names) < 3 or not all(parts) or len({(m.group(1), m.group(3)) for m in parts}) != 1:
        return None
    steps = np.diff([int(m.group(2)) for m in parts])
    usual = float(np.median(steps))
    big = np.flatnonzero(steps > GAP_FACTOR * usual)
    if usual <= 0 or not big.size:
        return None
    i = int(big[0])
    return names[i], names[i + 1], int(steps[i]), int(round(usual))


def numbering_gap_caution(src: str, names: list[str]) -> str | None:
    """What to warn of when the frames' numbers skip (numbering_gap) while their times come from a frame rate: by
    position, the frames after the gap would be early by the missing frames' time; None when they do not skip."""
    gap = numbering_gap(names)
    if gap is None:
        return None
    a, b, step, usual = gap
    return (f"source {src!r}: the frame numbers skip from {a!r} to {b!r} (a step of {step}; the others {usual}): "
            "`rate_hz` times frame k at k / rate_hz s by its position, so the frames after the gap are early by "
            "the missing frames' time; give `timestamps` (columns file,t_s) if frames are missing")


def decimal_names_caution(src: str, names: list[str]) -> str | None:
    """What to warn of when the names end in decimal numbers of unequal decimals (t_12.5.png, t_12.25.png: times in
    s, most likely): natural order compares 5 and 25 as whole numbers and puts 12.5 first, so the frames are out of
    time order under a frame rate; None otherwise."""
    parts = [re.fullmatch(r".*?\d+\.(\d+)", os.path.splitext(n)[0]) for n in names]
    if len(names) < 2 or not all(parts) or len({len(m.group(1)) for m in parts}) < 2:
        return None
    short, long_ = (min(names, key=lambda n: len(n)), max(names, key=lambda n: len(n)))
    return (f"source {src!r}: the names end in decimal numbers of unequal decimals ({short!r}, {long_!r}): name order "
            "compares their decimals as whole numbers (12.5 before 12.25), so the frames may be out of time order; "
            "give `timestamps` (columns file,t_s), or names with as many decimals each")


def spacing_caution(src: str, t_s: np.ndarray, frames: int, max_gap_s: float) -> str | None:
    """What to warn of when no `frames` frames in a row are within max_gap_s of the one before (the cold start's
    window, [tracker.acquire] frames and max_gap_s): the tracker cannot start on them, so nothing is tracked (it
    was said without a reason); None when some are."""
    run = longest = 0
    for close in np.diff(t_s) <= max_gap_s:
        run = run + 1 if close else 0
        longest = max(longest, run)
    if longest + 1 >= frames:
        return None
    return (f"source {src!r}: no {frames} frames in a row are within {max_gap_s:g} s of the one before (the frames are "
            f"a median {np.median(np.diff(t_s)):.3g} s apart; [tracker.acquire] frames and max_gap_s): the cold "
            "start cannot gather its window, so nothing will be tracked; times in ms? (t_s is in s)")


def rate_times(src: str, n: int, rate_hz: float) -> np.ndarray:
    """Times (n,) s of n frames at rate_hz (frame k at k / rate_hz); InputError when the last is beyond the
    recording's clock (MAX_TIME_S: a rate in Hz given in mHz or less, the clock overflowed after tracking)."""
    if (n - 1) / rate_hz > MAX_TIME_S:
        raise InputError(f"rate_hz {rate_hz:g}: frame {n - 1} of {src!r} would be at {(n - 1) / rate_hz:.3g} s, "
                         f"beyond the recording's clock ({MAX_TIME_S:.3g} s, int64 ns); expected a frame rate in Hz")
    return np.arange(n) / rate_hz


def read_timestamps(path: str, files: list[str]) -> np.ndarray:
    """Frame times (N,) s from a CSV with columns file,t_s for the given image files (matched by file name: a
    path's last name, / or \\ its separator); InputError naming the CSV (and the line) when it has no such columns,
    a row misses a value, a file has two different times or none, or the times do not increase in the files'
    order by at least MIN_FRAME_DT_S (spaced_times)."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:  # utf-8-sig: a spreadsheet's byte-order mark
            reader = csv.reader(fh)
            header = [h.strip() for h in next(reader, [])]
            rows = list(reader)
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"timestamps {path!r}: cannot be read ({getattr(err, 'strerror', None) or err})") from None
    if not {"file", "t_s"} <= set(header):
        raise InputError(f"{path}: header {','.join(header)!r}: expected a CSV with a header line and columns "
                         "file,t_s (comma-separated)")
    col_f, col_t = header.index("file"), header.index("t_s")
    times: dict[str, float] = {}
    lines: dict[str, int] = {}
    for n, row in enumerate(rows, start=2):
        if not any(v.strip() for v in row):
            continue  # a blank line
        if len(row) <= max(col_f, col_t):
            raise InputError(f"{path}: line {n}: {','.join(row)!r}: expected a file and a time t_s (s)")
        name, t = ntpath.basename(row[col_f].strip()), row[col_t].strip()  # a Windows path's name too (C:\\...)
        try:
            value = float(t)
        except ValueError:
            raise InputError(f"{path}: line {n}: t_s = {t!r}: expected a time in s") from None
        if name in times and times[name] != value:
            raise InputError(f"{path}: line {n}: {name!r} at t = {value} s, but t = {times[name]} s on an earlier "
                             "line: expected one time per image")
        times[name] = value
        lines.setdefault(name, n)
    t = []
    for f in files:
        name = os.path.basename(f)
        if name not in times:
            raise InputError(f"{path}: no time for image {name!r} (expected a row file,t_s for every image)")
        t.append(times[name])
    return increasing_times(path, np.array(t), files, [lines[os.path.basename(f)] for f in files])


def increasing_times(path: str, t: np.ndarray, files: list[str], lines: list[int] | None = None) -> np.ndarray:
    """t when its times are finite and increase in the files' order (spaced_times); else InputError naming the first
    file at fault and its time (and its line of the CSV, lines (N,) where given)."""
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        k = int(bad[0])
        raise InputError(f"{path}: {os.path.basename(files[k])} at t = {t[k]} s: expected a finite time in s")
    bad = np.flatnonzero(np.abs(t) > MAX_TIME_S)
    if bad.size:  # ms since 1970 read as s: tracked, then the recording's clock overflowed (a traceback)
        k = int(bad[0])
        raise InputError(f"{path}: {os.path.basename(files[k])} at t = {t[k]:.6g} s: expected a time in s of at most "
                         f"{MAX_TIME_S:.3g} s in size (292 years: the recording's clock, int64 ns); times in ms or "
                         "us since an epoch? (t_s is in s)")
    return spaced_times(path, t, files, lines)


def spaced_times(path: str, t: np.ndarray, files: list[str], lines: list[int] | None = None) -> np.ndarray:
    """t when each time follows the one before (in the files' order) by at least MIN_FRAME_DT_S, the least step of
    the truth's physics and of the filter's RK4 (the floor `rate_hz` keeps too: 10 kHz); else InputError naming the
    first pair: the later file (its CSV line, lines (N,) where given), both times and the floor. Two frames 1e-6 s
    apart were tracked as frames 1e-6 s apart. The floor is met within the times' rounding (1e-4 s steps since an
    epoch differ by a few ulps from 1e-4)."""
    dt = np.diff(t)
    slack = 4.0 * np.spacing(np.maximum(np.abs(t[1:]), np.abs(t[:-1]))) + 1e-9 * MIN_FRAME_DT_S
    close = np.flatnonzero(dt < MIN_FRAME_DT_S - slack)
    if not close.size:
        return t
    k = int(close[0]) + 1
    a, b = os.path.basename(files[k - 1]), os.path.basename(files[k])
    where = f"line {lines[k]}: " if lines else ""
    earlier = f" (line {lines[k - 1]})" if lines else ""
    if dt[k - 1] <= 0:
        said = "does not follow"
    else:
        said = f"is {dt[k - 1]:.3g} s after"
    raise InputError(f"{path}: {where}{b} at t = {t[k]} s {said} {a} at t = {t[k - 1]} s{earlier}: expected times "
                     f"that increase in the images' name order by at least {MIN_FRAME_DT_S:g} s (the least step of "
                     "the physics and the filter: a camera of at most 10 kHz)")
