"""The frames of `envisat track` as users have them: a sequence-mode generate folder, a folder of image files or a
video (`open_source`), every frame read once before any output (`scan_source`).

- Image folders: PNG, JPEG, TIFF, BMP, PGM/PPM or WebP files; hidden and dot files (macOS `._*`) are ignored; names are sorted
  naturally and their times read or warned of as pipelines/runs/frame_names.py says (two files of one frame
  number refused; numbered names that skip numbers under a frame rate warned of). One image file is refused (its
  folder is the sequence), and so is a file of several frames (a TIFF stack, an animation); a video whose header
  counts more frames than can be read is warned of.
- Pixels: 8-bit files as they are; 16-bit files hold `bit_depth`-bit data (10, 12, 14 or 16; default: the
  smallest depth that holds the sequence's maximum), scaled to 8 bits by 255 / (2^bit_depth - 1). Colour or gray
  with alpha, and a PNG's transparent colour, are composited over black (space is black); an EXIF Orientation is
  not applied: the pixels are as stored, which the intrinsics describe, and frames that carry one are warned of
  (pipelines/runs/frame_pixels.py); so is a video's rotation metadata (pipelines/runs/frame_video.py).
- Messages the image and video libraries print (OpenCV, libpng, libtiff, FFmpeg) are kept off the terminal
  (`native_stderr`); what they said goes into the one-line InputError when a frame cannot be read.
"""

from __future__ import annotations

import contextlib
import os
import sys
import warnings
from dataclasses import dataclass, field

import numpy as np

from envisat_pose.config import ConfigError, InputError
from envisat_pose.datagen.generate_config import nest_moved_keys
from envisat_pose.geometry import MIN_SIDE_PX
from envisat_pose.pipelines.detector.detect_target import require_dataset_of
from envisat_pose.pipelines.runs.frame_names import (
    IMAGE_EXTENSIONS,
    decimal_names_caution,
    numbering_gap_caution,
    rate_times,
    read_timestamps,
    sorted_frames,
    unread_images_caution,
    unread_images_said,
)
from envisat_pose.pipelines.runs.frame_pixels import (
    as_stored,
    black_is_zero,
    gray_alpha_pixels,
    gray_alpha_tiff,
    keyed_over_black,
    orientation_caution,
    over_black,
    png_gray_key,
    premultiplied,
)
from envisat_pose.pipelines.runs.frame_video import open_video
from envisat_pose.resumable import manifest_path
from envisat_pose.shard_reader import checked_shards, load_dataset_manifest
from envisat_pose.target import DEFAULT_TARGET, load_target, other_target, require_envisat_dataset

BIT_DEPTHS = (8, 10, 12, 14, 16)


# ---------------------------------------------------------------------------------------------------------
# Third-party messages


@contextlib.contextmanager
def native_stderr():
    """Send what native libraries write to file descriptor 2 into a temporary file for the block; yields a list
    that holds, after the block, the text they wrote (for the error message, never the terminal)."""
    import tempfile

    said: list[str] = []
    with contextlib.suppress(Exception):
        sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield said
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            said.append(tmp.read().decode("utf-8", "replace"))


def library_said(said: list[str]) -> str:
    """' (the library: its last line)' from native_stderr's capture, '' when it said nothing."""
    lines = [ln.strip() for ln in "".join(said).splitlines() if ln.strip()]
    if not lines:
        return ""
    last = lines[-1]
    return f" ({last[:160]})"


# ---------------------------------------------------------------------------------------------------------
# Pixels


def to_gray(img: np.ndarray | None, name: str, said: list[str] | None = None,
            is_premultiplied: bool = False) -> np.ndarray:
    """8- or 16-bit gray or colour (BGR/BGRA, OpenCV's order; gray+alpha) -> (H, W) gray of the same depth; colour
    with alpha composited over black first (frame_pixels.over_black: space is black, not the colour a transparent
    pixel stores; is_premultiplied: the colour is so already)."""
    import cv2

    if img is None or img.size == 0:
        raise InputError(f"{name}: cannot be read as an image (expected PNG, JPEG, TIFF, BMP, PGM/PPM or WebP)"
                         + library_said(said or []))
    if img.dtype not in (np.uint8, np.uint16):
        raise InputError(f"{name}: pixels of type {img.dtype}: expected unsigned 8- or 16-bit integers (uint8, "
                         "uint16)")  # a signed 16-bit TIFF was told it was not 16-bit
    if img.ndim == 3 and img.shape[2] in (2, 4):
        img = over_black(img, is_premultiplied)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return np.ascontiguousarray(img)


def to_u8(img: np.ndarray, bit_depth: int) -> np.ndarray:
    """A gray frame of bit_depth-bit data (uint8 or uint16) as uint8: round(v x 255 / (2^bit_depth - 1))."""
    if img.dtype == np.uint8:
        return img
    full = (1 << bit_depth) - 1
    v = np.minimum(img.astype(np.uint32), full)
    return ((v * 255 + full // 2) // full).astype(np.uint8)


def read_gray(path: str, turned: list[tuple[str, int]] | None = None) -> np.ndarray:
    """An image file as (H, W) gray, uint8 or uint16 as stored (not turned by an EXIF Orientation: turned, when
    given, gets (path, its Orientation) for one other than 1); InputError naming the file when it is unreadable or
    truncated (with what the image library said)."""
    import cv2

    try:
        with open(path, "rb") as fh:
            raw, orientation, extra = as_stored(fh.read())
    except OSError as err:
        raise InputError(f"{path}: cannot be read ({err.strerror or err})") from None
    gray_alpha = gray_alpha_tiff(raw, path)
    data = np.frombuffer(gray_alpha.data if gray_alpha else raw, np.uint8)
    with native_stderr() as said:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        pages = frame_count(path) if img is not None else 1
    img = gray_alpha_pixels(img, gray_alpha) if gray_alpha else keyed_over_black(black_is_zero(img, raw),
                                                                                 png_gray_key(raw))
    if img is not None and path.lower().endswith((".jpg", ".jpeg")) and not data[-2:].tobytes() == b"\xff\xd9":
        img = None  # OpenCV decodes a truncated JPEG with a grey tail and a warning; it is not a whole frame
        said.append("the JPEG data ends before its end marker")
    if pages > 1:  # imdecode gives the first page alone: the rest of the stack was lost without a word
        raise InputError(f"{path}: {pages} frames in one file (a multi-page TIFF or an animation); expected one "
                         "frame per file: save each page as its own file")
    gray = to_gray(img, path, said, img is not None and (gray_alpha.premultiplied if gray_alpha else
                                                        premultiplied(extra, img.dtype)))
    if orientation != 1 and turned is not None:
        turned.append((path, orientation))
    return gray


def frame_count(path: str) -> int:
    """The frames an image file holds (the pages of a TIFF stack, an animated PNG's or WebP's frames; 1 for most
    files), from its header; 1 when OpenCV cannot say, or for a name that is not UTF-8 (OpenCV's readers by path
    crash on one)."""
    import cv2

    if not is_utf8(path):
        return 1
    try:
        return max(int(cv2.imcount(path)), 1)
    except cv2.error:
        return 1


def detect_bit_depth(max_value: int) -> int:
    """The smallest of 10, 12, 14, 16 bits that holds a 16-bit sequence's maximum value."""
    for bits in BIT_DEPTHS[1:]:
        if max_value < (1 << bits):
            return bits
    return 16


# ---------------------------------------------------------------------------------------------------------
# Sources


@dataclass
class FrameSource:
    """The frames of one input. kind: 'dataset', 'images' or 'video'; path; t_s (N,) s; names (N,) what each frame
    is called in messages (file, sample key, frame index); truth: None or {x (N, 12), corners_px (N, K, 2),
    in_frame (N, K), eclipse (N,) the target unlit in the Earth's shadow} from a dataset's labels (K: its target's keypoints, ENVISAT's 8 corners); scenario: a
    dataset's own scenario (None otherwise); files: an image folder's files in time order (a dataset's: its checked
    shard files); bit_depth: the data's bits (8, or 10-16 in 16-bit files: scan_source sets it); size_px: (width,
    height) of every frame (scan_source); skipped: a dataset's damaged shards left out (open_source's
    skip_damaged); target: a dataset's target as its manifest records it ({name, sha256}; None for frames without
    one, and for a dataset written before targets were recorded: ENVISAT's); cautions: what scan_source warns of
    once the frames pass (numbered names that skip under a frame rate, a video cut short), not before a refusal."""

    kind: str
    path: str
    t_s: np.ndarray
    names: list[str]
    truth: dict | None = None
    scenario: str | None = None
    files: list[str] = field(default_factory=list)
    bit_depth: int = 8
    size_px: tuple[int, int] | None = None
    skipped: list[str] = field(default_factory=list)
    target: dict | None = None
    cautions: list[str] = field(default_factory=list)

    def where(self, i: int) -> str:
        """Frame i as a message names it: the file, or the input and the frame."""
        return self.files[i] if self.kind == "images" else f"{self.path}: {self.names[i]}"

    def raw_frames(self, turned: list[tuple[str, int]] | None = None):
        """(index, gray image as stored: uint8 or uint16) in time order; InputError naming the frame when one cannot
        be read. turned, when given, gets (file, its EXIF Orientation) for each image file of one other than 1."""
        if self.kind == "images":
            for i, f in enumerate(self.files):
                yield i, read_gray(f, turned)
        elif self.kind == "video":
            with native_stderr() as said:
                cap, _ = open_video(self.path)
            try:
                for i in range(len(self.t_s)):
                    with native_stderr() as said:
                        ok, img = cap.read()
                    if not ok:
                        raise InputError(f"{self.path}: frame {i} cannot be read (expected {len(self.t_s)} frames)"
                                         + library_said(said))
                    yield i, to_gray(img, f"{self.path} frame {i}")
            finally:
                cap.release()
        else:
            from envisat_pose.datagen.dataset import iter_samples, sample_image

            for i, (key, label, members) in enumerate(iter_samples(self.files)):
                try:
                    with native_stderr():
                        img = sample_image(members, label)
                except Exception as err:  # a damaged PNG member
                    raise InputError(f"{self.path}: sample {key}: image cannot be read ({err})") from None
                yield i, img

    def frames(self):
        """(index, gray uint8 image) in time order (16-bit data scaled from bit_depth bits)."""
        for i, img in self.raw_frames():
            yield i, to_u8(img, self.bit_depth)


def open_source(source: str, rate_hz: float = 0.0, timestamps: str | None = None,
                bit_depth: int | None = None, skip_damaged: bool = False) -> FrameSource:
    """Returns a FrameSource: the frames of `source` (a generate folder, an image folder or a video file) with their
    times (t_s, s), its kind and, for a generate folder, its truth (class FrameSource). InputError with one line
    naming the input and what was expected, or the flag that does not apply to it. bit_depth: of the
    data in 16-bit image files (None: detected by scan_source). A generate folder's shards are checked against
    its manifest: a damaged one is refused, or with skip_damaged left out (the FrameSource's skipped names it)."""
    if bit_depth is not None and bit_depth not in BIT_DEPTHS:
        raise InputError(f"bit_depth {bit_depth}: expected one of {', '.join(map(str, BIT_DEPTHS))}")
    rate_hz = 0.0 if rate_hz is None else float(rate_hz)
    if rate_hz and not (np.isfinite(rate_hz) and rate_hz > 0):
        raise InputError(f"rate_hz {rate_hz}: expected a positive, finite frame rate, Hz")
    if rate_hz and timestamps:
        raise InputError("rate_hz and `timestamps`: give one of them (the frame times)")
    if os.path.isdir(source):
        try:
            names = os.listdir(source)
        except OSError as err:  # a folder of another user's without read permission: a traceback
            raise InputError(f"source {source!r}: the folder cannot be listed ({err.strerror or err})") from None
        if os.path.isfile(manifest_path(source)) and generate_folder(source, names):
            for flag, value in (("rate_hz", rate_hz), ("timestamps", timestamps), ("bit_depth", bit_depth)):
                if value:
                    raise InputError(f"{flag} does not apply to a generate folder ({source!r}: its labels give the "
                                     "frame times and its frames are 8-bit)")
            return dataset_source(source, skip_damaged)
        files = [os.path.join(source, f) for f in sorted_frames(source, names)]
        if not files:
            unread = unread_images_said(names)
            raise InputError(f"source {source!r}: no image files (expected PNG, JPEG, TIFF, BMP, PGM/PPM or WebP "
                             "files, a generate folder or a video)" + (f"; {unread}" if unread else ""))
        if timestamps:
            t = read_timestamps(timestamps, files)
        elif rate_hz > 0:
            t = rate_times(source, len(files), rate_hz)
        else:
            raise InputError(f"source {source!r}: a folder of images needs a frame rate (`rate_hz`) or "
                             "a timestamps file (`timestamps`)")
        frames = FrameSource("images", source, t, [os.path.basename(f) for f in files], files=files)
        unread = unread_images_caution(source, names)
        frames.cautions += [unread] if unread else []
        if not timestamps:  # names that may not be in time order, or may miss frames, under a frame rate
            caution = decimal_names_caution(source, frames.names) or numbering_gap_caution(source, frames.names)
            frames.cautions += [caution] if caution else []
    elif os.path.isfile(source):
        if source.lower().endswith(IMAGE_EXTENSIONS) and frame_count(source) > 1:
            raise InputError(f"source {source!r}: {frame_count(source)} frames in one image file (a multi-page TIFF "
                             "or an animation); expected a folder of one frame per file (save each page as its own "
                             "file), a video or a generate folder")
        if source.lower().endswith(IMAGE_EXTENSIONS):
            raise InputError(f"source {source!r}: one image file; expected the folder of the sequence's frames "
                             f"({os.path.dirname(source) or '.'!r}), a video or a generate folder")
        if timestamps:
            raise InputError(f"timestamps does not apply to a video ({source!r}): its frames are at `rate_hz` or the "
                             "file's own frame rate")
        if bit_depth:
            raise InputError(f"bit_depth does not apply to a video ({source!r}): its frames are 8-bit")
        if not is_utf8(source):  # OpenCV's video reader crashed the process (a segfault) on such a path
            raise InputError(f"source {source!r}: a file name that is not UTF-8; expected a video whose path is UTF-8 "
                             "(OpenCV's video reader takes no other): rename it")
        frames = video_source(source, rate_hz)
    else:
        raise InputError(f"source {source!r}: no such file or folder")
    frames.bit_depth = bit_depth or 0  # 0: detect (scan_source)
    return frames


def generate_folder(src: str, names: list[str]) -> bool:
    """Whether a folder with a manifest.json (names: its files) is a generate folder: its manifest a dataset's, or
    no image files beside it (dataset_source then says what is wrong with it). Another tool's manifest.json beside a
    user's images (a labelling tool's, an exporter's) leaves the folder an image folder: it was refused as a damaged
    dataset."""
    try:
        load_dataset_manifest(src, "source")
    except InputError:
        return not any(n.lower().endswith(IMAGE_EXTENSIONS) for n in names)
    return True


def is_utf8(path: str) -> bool:
    """Whether a path's name is UTF-8 (os.listdir and the shell hand on other bytes as surrogates)."""
    try:
        path.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def video_source(path: str, rate_hz: float) -> FrameSource:
    """A video's frames, counted; its times at rate_hz or its own rate; its rotation metadata not applied (the frames
    as stored, warned of: frame_video.open_video); InputError naming the video when it has no frames to track."""
    import cv2

    with native_stderr() as said:
        cap, turned = open_video(path)
        try:
            opened = cap.isOpened()
            header = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0) if opened else 0
            n = 0
            while opened and cap.grab():
                n += 1
            fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0) if opened else 0.0
        finally:
            cap.release()
    if not opened:
        raise InputError(f"source {path!r}: cannot be opened as a video (expected a video file OpenCV reads, "
                         "an image folder or a generate folder)" + library_said(said))
    if n == 0:
        raise InputError(f"source {path!r}: the video has no readable frames" + library_said(said))
    rate = rate_hz if rate_hz > 0 else fps
    if not rate > 0:
        raise InputError(f"source {path!r}: the video has no frame rate: give `rate_hz`")
    source = FrameSource("video", path, rate_times(path, n, rate), [f"frame {i}" for i in range(n)], cautions=turned)
    if n < header:  # a file cut short (a copy or a recording that stopped) still opens: its tail is gone
        source.cautions.append(f"source {path!r}: {n} of the {header} frames the video's header counts can be read: "
                               f"tracking those {n} (a truncated file?)" + library_said(said))
    return source


def dataset_source(path: str, skip_damaged: bool = False) -> FrameSource:
    """A sequence-mode generate folder of any target: times, truth and scenario from the labels and the manifest,
    the target from the manifest's record (source.target; a job checks it against its own: require_source_target);
    its shards checked against the manifest (shard_reader.checked_shards: a damaged one refused, or left out with
    skip_damaged: its frames are then missing from the sequence, the times say where). The truth's pixels are the
    labels' corners_px (ENVISAT's) or keypoints_px (another target's, K of them, named by keypoint_names)."""
    from envisat_pose.datagen.dataset import iter_samples

    manifest = load_dataset_manifest(path, "source")
    cfg = manifest.get("config", {})
    if cfg.get("mode") != "sequence":
        raise InputError(f"source {path!r}: a generate folder of mode {cfg.get('mode')!r}; expected one written "
                         "in sequence mode (`envisat generate --mode sequence`: frames in time order)")
    if not manifest.get("complete"):
        raise InputError(f"source {path!r}: an unfinished dataset (run `envisat generate` on it again to finish it)")
    files, skipped = checked_shards(path, skip_damaged, "source")
    t, names, x, uv, inf, dark = [], [], [], [], [], []
    for key, label, _ in iter_samples(files):
        t.append(float(label["scene"]["t_s"]))
        names.append(key)
        x.append(label["x"])
        uv.append(label["keypoints_px"] if "keypoint_names" in label else label["corners_px"])
        inf.append(np.asarray(label["in_frame"], bool) & np.asarray(label["visible"], bool))
        dark.append(bool(label["scene"].get("eclipse")))
    truth = {"x": np.array(x, float), "corners_px": np.array(uv, float), "in_frame": np.array(inf),
             "eclipse": np.array(dark, bool)}
    record = manifest.get("target")
    target = {"name": record.get("name"), "sha256": record.get("sha256")} if isinstance(record, dict) else None
    return FrameSource("dataset", path, np.array(t), names, truth=truth,
                       scenario=nest_moved_keys(cfg).get("sequence", {}).get("scenario"), files=files,
                       skipped=skipped, target=target)


def require_source_target(source: FrameSource, target: str = DEFAULT_TARGET, field: str = "source") -> None:
    """InputError in one line unless a generate folder's frames show the job's target (its `target` value, a
    file): ENVISAT's datasets for ENVISAT (target.require_envisat_dataset: its name and corners, or none recorded),
    the same file's sha256 for another (detect_target.require_dataset_of). Image folders and videos record no
    target: they pass."""
    if source.kind != "dataset":
        return
    if other_target(target) is not None:
        require_dataset_of(source.path, load_target(target, "target"), field)
        return
    try:
        require_envisat_dataset(source.path, field, "track")
    except ConfigError:
        name = (source.target or {}).get("name")
        raise InputError(f"{field} {source.path!r}: a dataset of target {name!r}, not of ENVISAT ({DEFAULT_TARGET}, "
                         "the job's target): track it with its target file and that target's keypoint detector "
                         "(`envisat track --target FILE.xml --weights W`; `envisat adapt` knows ENVISAT only)"
                         ) from None


# ---------------------------------------------------------------------------------------------------------
# Every frame once, before any output


def scan_source(source: FrameSource, size_px: tuple[int, int] | None = None, min_frames: int = 1,
                progress: bool = False) -> str:
    """Read every frame once before any output: each must decode, be at least MIN_SIDE_PX a side and have one
    size (size_px (width, height): the camera's; None: the size most frames have, so the odd frame is the one
    named); 16-bit data must fit the bit depth (detected when 0); then source.cautions are warned of (once), with
    image files of an EXIF Orientation other than 1 (frame_pixels.orientation_caution).
    Sets source.size_px and source.bit_depth;
    returns a line saying what the pixels are. InputError naming the frame at fault, or the frame count when
    there are fewer than min_frames (the tracker's cold start needs that many)."""
    turned: list[tuple[str, int]] = []
    it = source.raw_frames(turned)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, total=len(source.t_s), unit="frame", desc="checking frames", mininterval=0.5)
    T = len(source.t_s)
    shapes = np.zeros((T, 2), np.int64)
    wide = np.zeros(T, bool)
    peak = np.zeros(T, np.int64)
    for i, img in it:
        shapes[i], wide[i], peak[i] = img.shape, img.dtype == np.uint16, int(img.max()) if img.size else 0
    if size_px is not None:
        want = (int(size_px[1]), int(size_px[0]))
    else:
        sizes, counts = np.unique(shapes, axis=0, return_counts=True)
        best = sizes[counts == counts.max()]
        want = tuple(shapes[0]) if any((s == shapes[0]).all() for s in best) else tuple(best[0])
    bad = np.flatnonzero((shapes != want).any(axis=1))
    if bad.size:
        i = int(bad[0])
        like = "like the camera" if size_px is not None else f"like {T - bad.size} of the {T} frames"
        raise InputError(f"{source.where(i)}: image is {shapes[i, 1]} x {shapes[i, 0]} px; expected {want[1]} x "
                         f"{want[0]} px {like} (all frames one size; a `camera` file for another camera)")
    if min(want) < MIN_SIDE_PX:
        raise InputError(f"{source.where(0)}: image is {want[1]} x {want[0]} px; expected at least {MIN_SIDE_PX} px "
                         "a side")
    if wide.any() and not wide.all():
        i = int(np.flatnonzero(wide != wide[0])[0])
        raise InputError(f"{source.where(i)}: a {16 if wide[i] else 8}-bit image among {8 if wide[i] else 16}-bit "
                         "frames: expected one bit depth for the sequence")
    source.size_px = (int(want[1]), int(want[0]))
    if not wide.any():
        if source.bit_depth not in (0, 8):
            raise InputError(f"bit_depth {source.bit_depth} does not apply: the frames are 8-bit files (it gives "
                             "the depth of the data in 16-bit files)")
        source.bit_depth = 8
        line = "8-bit frames"
    else:
        top = int(peak.max())
        if source.bit_depth:
            over = np.flatnonzero(peak >= (1 << source.bit_depth))
            if over.size:
                i = int(over[0])
                raise InputError(f"{source.where(i)}: pixel value {peak[i]} does not fit `bit_depth` "
                                 f"{source.bit_depth} (at most {(1 << source.bit_depth) - 1})")
            line = f"16-bit files of {source.bit_depth}-bit data (--bit-depth; maximum {top})"
        else:
            source.bit_depth = detect_bit_depth(top)
            line = (f"16-bit files of {source.bit_depth}-bit data (detected from the maximum {top} over "
                    f"{T} frames; --bit-depth to set it" + ("; every value fits 8 bits: --bit-depth 8 if the files "
                                                            "hold 8-bit data)" if top < 256 else ")"))
        line += f": scaled to 8 bits by 255/{(1 << source.bit_depth) - 1}"
    if T < min_frames:
        raise InputError(f"source {source.path!r}: {T} frame(s); the tracker's cold start needs at least "
                         f"{min_frames} (tracker.acquire.frames)")
    source.cautions += orientation_caution(source.path, turned, T, source.size_px)
    for text in source.cautions:  # once, and only for frames that pass: a refusal stays one line
        warnings.warn(text, stacklevel=2)
    source.cautions = []
    return line
