"""What a user's image file says of its pixels beyond what OpenCV's decode returns (pipelines/runs/frames.py reads
the frames with it):

- The EXIF Orientation (tag 274, in a JPEG's APP1 Exif segment, a TIFF's first directory, a PNG's eXIf chunk or a
  WebP's EXIF chunk): how a viewer turns the stored pixels for display. Pose needs the pixels as stored (the
  camera's intrinsics describe the sensor's pixels): `as_stored` sets the tag to 1 in the bytes given to the
  decoder (OpenCV's TIFF reader turns the pixels by it, some versions only partly; its JPEG reader does not),
  and `orientation_caution` tells the user once per source.
- Alpha: space is black, so colour with alpha (BGRA, gray+alpha) is composited over black (`over_black`). A TIFF's
  ExtraSamples (tag 338) says whether its colour is premultiplied already: associated alpha (1) is, and so is
  unassociated alpha (2) in an 8-bit colour TIFF, which OpenCV reads through libtiff's RGBA reader that
  premultiplies. A gray+alpha TIFF OpenCV gives as one 8-bit channel without its alpha: told it is one sample of
  twice the width, it gives both at the file's depth (`gray_alpha_tiff`, `gray_alpha_pixels`; its gray is as stored,
  premultiplied for associated alpha only).
- White is zero: a gray TIFF stored white-is-zero (Photometric 0) OpenCV gives inverted (0 black) at 8 bits (libtiff's
  RGBA reader) but as stored at 16 (read sample by sample): `black_is_zero` inverts a 16-bit one where this OpenCV
  does not (asked once of a 1 px file, `decoder_inverts_16_bit_white_is_zero`), so both depths come as one picture.
- Transparency without alpha: a gray PNG's tRNS value is composited over black like an alpha of 0 (`png_gray_key`,
  `keyed_over_black`: OpenCV drops it); a palette's or an RGB PNG's tRNS OpenCV gives as an alpha channel.
"""

from __future__ import annotations

import functools
import struct
from dataclasses import dataclass

import numpy as np

from envisat_pose.config_errors import InputError

ORIENTATION_TAG = 274
EXTRA_SAMPLES_TAG = 338
# how a viewer shows the stored pixels, by Orientation (1: as stored)
SHOWN = {2: "mirrored left-right", 3: "turned 180 deg", 4: "mirrored top-bottom",
         5: "mirrored and turned 90 deg (transposed)", 6: "turned 90 deg clockwise",
         7: "mirrored and turned 90 deg (transversed)", 8: "turned 90 deg counter-clockwise"}
JPEG_EXIF = b"Exif\0\0"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def tiff_header_at(data: bytes) -> int | None:
    """Where the TIFF header that holds a file's tags starts in data: 0 for a TIFF file, after 'Exif\\0\\0' in a
    JPEG's APP1 segment (before its scan), a PNG's eXIf chunk, a WebP's EXIF chunk; None when there is none."""
    if data[:4] in (b"II*\0", b"MM\0*"):
        return 0
    if data[:2] == b"\xff\xd8":  # JPEG: marker segments up to the start of scan
        i = 2
        while i + 4 <= len(data) and data[i] == 0xFF:
            marker = data[i + 1]
            if marker in (0xD9, 0xDA):
                return None
            if marker == 0xFF or 0xD0 <= marker <= 0xD7 or marker == 0x01:  # fill byte, markers without a length
                i += 1 if marker == 0xFF else 2
                continue
            if marker == 0xE1 and data[i + 4:i + 10] == JPEG_EXIF:
                return i + 10
            i += 2 + int.from_bytes(data[i + 2:i + 4], "big")
        return None
    if data[:8] == PNG_SIGNATURE:
        i = 8
        while i + 8 <= len(data) and data[i + 4:i + 8] != b"IEND":
            if data[i + 4:i + 8] == b"eXIf":
                return i + 8
            i += 12 + int.from_bytes(data[i:i + 4], "big")
        return None
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        i = 12
        while i + 8 <= len(data):
            size = int.from_bytes(data[i + 4:i + 8], "little")
            if data[i:i + 4] == b"EXIF":  # some writers keep JPEG's prefix
                return i + 8 + (6 if data[i + 8:i + 14] == JPEG_EXIF else 0)
            i += 8 + size + (size & 1)
    return None


def tiff_directory(data: bytes) -> tuple[str, dict[int, tuple[int, int, int, int]]] | None:
    """The first directory of data's TIFF header (tiff_header_at): (byte order 'little' or 'big', {tag: (type,
    count, where its values lie in data, where its entry lies)}); None without one, or where the header is damaged
    (a header that cannot be read tells of no tag: the decoder has the last word on the pixels)."""
    base = tiff_header_at(data)
    order = None if base is None else {b"II": "little", b"MM": "big"}.get(bytes(data[base:base + 2]))
    if order is None:
        return None

    def u(at: int, n: int) -> int:
        return int.from_bytes(data[at:at + n], order)

    if u(base + 2, 2) != 42:  # a BigTIFF (43) or no TIFF header
        return None
    ifd = base + u(base + 4, 4)
    entries: dict[int, tuple[int, int, int, int]] = {}
    for k in range(u(ifd, 2) if ifd + 2 <= len(data) else 0):
        at = ifd + 2 + 12 * k
        if at + 12 > len(data):
            break
        tag, kind, count = u(at, 2), u(at + 2, 2), u(at + 4, 4)
        inline = {3: 2, 4: 4}.get(kind, 8) * count <= 4  # SHORTs, LONGs: up to 4 bytes in the entry, more at an offset
        entries.setdefault(tag, (kind, count, at + 8 if inline else base + u(at + 8, 4), at))
    return order, entries


def tiff_value(data: bytes, directory: tuple[str, dict], tag: int, default: int | None = None) -> int | None:
    """The first value of a SHORT or LONG tag of a tiff_directory; default when it is absent or of another type."""
    order, entries = directory
    kind, count, where, _ = entries.get(tag, (0, 0, 0, 0))
    n = {3: 2, 4: 4}.get(kind, 0)
    if not n or count < 1 or where + n > len(data):
        return default
    return int.from_bytes(data[where:where + n], order)


def header_shorts(data: bytes, tags: tuple[int, ...] = (ORIENTATION_TAG, EXTRA_SAMPLES_TAG)) -> dict:
    """The first value of each of `tags` that the first directory of data's TIFF header (tiff_header_at) holds as
    SHORTs: {tag: (value, its offset in data, byte order 'little' or 'big')}; {} without one, or where the header
    is damaged."""
    directory = tiff_directory(data)
    if directory is None:
        return {}
    order, entries = directory
    return {tag: (tiff_value(data, directory, tag), entries[tag][2], order) for tag in tags
            if tag in entries and entries[tag][0] == 3 and tiff_value(data, directory, tag) is not None}


def as_stored(data: bytes) -> tuple[bytes, int, int]:
    """(data with its EXIF Orientation set to 1, so that no decoder turns the pixels; the Orientation it had, 1
    when none or not one of 2-8; a TIFF file's ExtraSamples, 0 when none or not a TIFF)."""
    tags = header_shorts(data)
    orientation, at, order = tags.get(ORIENTATION_TAG, (1, 0, "little"))
    if orientation in SHOWN:
        data = data[:at] + (1).to_bytes(2, order) + data[at + 2:]
    else:
        orientation = 1
    extra = tags.get(EXTRA_SAMPLES_TAG, (0,))[0] if data[:4] in (b"II*\0", b"MM\0*") else 0
    return data, orientation, extra


def premultiplied(extra_samples: int, dtype) -> bool:
    """Whether OpenCV gives a TIFF's colour premultiplied by its alpha: associated alpha (ExtraSamples 1) is stored
    so; unassociated alpha (2) is premultiplied by libtiff's RGBA reader, which OpenCV uses for 8-bit TIFFs."""
    return extra_samples == 1 or (extra_samples == 2 and np.dtype(dtype) == np.uint8)


# a gray+alpha TIFF (SamplesPerPixel 2): OpenCV reads it through libtiff's RGBA reader, as one 8-bit channel
# without its alpha (a 16-bit one at 8 bits too); told it is one sample of twice the width, it gives both samples
# at their depth (gray_alpha_tiff, then gray_alpha_pixels)
TIFF_WIDTH, TIFF_PHOTOMETRIC, TIFF_BITS, TIFF_COMPRESSION = 256, 262, 258, 259
TIFF_SAMPLES, TIFF_PREDICTOR, TIFF_PLANAR, TIFF_TILE_WIDTH, TIFF_SAMPLE_FORMAT = 277, 317, 284, 322, 339
PREDICTOR_CODECS = (5, 8, 32946, 34925, 50000)  # LZW, Deflate (2 codes), LZMA, ZSTD: libtiff applies a Predictor
SHORT, LONG = 3, 4


@dataclass(frozen=True)
class GrayAlpha:
    """A gray+alpha TIFF as OpenCV reads it whole: data (its bytes, told one sample of twice the width), width_px
    (the image's), run_px (the width over which its horizontal differencing restarts: 0 when there is none to
    undo), white_is_zero (Photometric 0: the gray inverted), premultiplied (associated alpha, ExtraSamples 1)."""

    data: bytes
    width_px: int
    run_px: int
    white_is_zero: bool
    premultiplied: bool


def gray_alpha_tiff(data: bytes, name: str) -> GrayAlpha | None:
    """GrayAlpha for a TIFF file of gray and one extra sample (SamplesPerPixel 2, Photometric 0 or 1, unsigned 8 or
    16 bits, samples interleaved); None for any other file. InputError naming the file for one whose samples lie in
    separate planes (PlanarConfiguration 2: OpenCV gives its gray alone)."""
    directory = tiff_directory(data) if data[:4] in (b"II*\0", b"MM\0*") else None
    if directory is None:
        return None
    order, entries = directory

    def value(tag: int, default: int | None = None) -> int | None:
        return tiff_value(data, directory, tag, default)

    if (value(TIFF_SAMPLES) != 2 or value(TIFF_PHOTOMETRIC) not in (0, 1) or value(TIFF_BITS) not in (8, 16)
            or value(TIFF_SAMPLE_FORMAT, 1) != 1 or value(TIFF_WIDTH) is None):
        return None
    if value(TIFF_PLANAR, 1) != 1:
        raise InputError(f"{name}: a gray+alpha TIFF whose gray and alpha lie in separate planes (PlanarConfiguration "
                         f"{value(TIFF_PLANAR)}); expected them interleaved (1, what most tools write): save it so")
    out = bytearray(data)

    def put(tag: int, kind: int, v: int) -> None:
        at = entries[tag][3]
        out[at + 2:at + 12] = (kind.to_bytes(2, order) + (1).to_bytes(4, order)
                               + v.to_bytes(2 if kind == SHORT else 4, order).ljust(4, b"\0"))

    width = value(TIFF_WIDTH)
    put(TIFF_WIDTH, LONG, 2 * width)
    tile = value(TIFF_TILE_WIDTH)
    if tile:
        put(TIFF_TILE_WIDTH, LONG, 2 * tile)
    put(TIFF_SAMPLES, SHORT, 1)
    put(TIFF_PHOTOMETRIC, SHORT, 1)  # libtiff's RGBA reader would invert the alpha too: gray_alpha_pixels inverts
    put(TIFF_BITS, SHORT, value(TIFF_BITS))
    if EXTRA_SAMPLES_TAG in entries:
        at = entries[EXTRA_SAMPLES_TAG][3]
        out[at + 4:at + 8] = (0).to_bytes(4, order)  # no extra sample in one sample a pixel
    run = 0
    if value(TIFF_PREDICTOR, 1) == 2 and value(TIFF_COMPRESSION, 1) in PREDICTOR_CODECS:
        put(TIFF_PREDICTOR, SHORT, 1)  # libtiff would undo it over single samples: gray_alpha_pixels does, by pixel
        run = tile or width
    return GrayAlpha(bytes(out), width, run, value(TIFF_PHOTOMETRIC) == 0, value(EXTRA_SAMPLES_TAG, 0) == 1)


def gray_alpha_pixels(img: np.ndarray | None, how: GrayAlpha) -> np.ndarray | None:
    """OpenCV's decode of gray_alpha_tiff's data ((H, 2 W) gray) as (H, W, 2) gray+alpha of the file's depth, its
    horizontal differencing undone (sums that wrap, as libtiff's); None when it is not that (to_gray says so)."""
    if img is None or img.ndim != 2 or img.shape[1] != 2 * how.width_px:
        return None
    pixels = img.reshape(img.shape[0], how.width_px, 2)
    for x0 in range(0, how.width_px, how.run_px) if how.run_px else ():
        run = pixels[:, x0:x0 + how.run_px]
        np.cumsum(run, axis=1, dtype=pixels.dtype, out=run)
    if how.white_is_zero:
        pixels[..., 0] = np.iinfo(pixels.dtype).max - pixels[..., 0]
    return pixels


def white_is_zero_16_bit(data: bytes) -> bool:
    """Whether data is a TIFF file of one 16-bit gray sample a pixel stored white-is-zero (Photometric 0)."""
    directory = tiff_directory(data) if data[:4] in (b"II*\0", b"MM\0*") else None
    if directory is None:
        return False
    return (tiff_value(data, directory, TIFF_PHOTOMETRIC) == 0 and tiff_value(data, directory, TIFF_SAMPLES, 1) == 1
            and tiff_value(data, directory, TIFF_BITS) == 16)


@functools.lru_cache(maxsize=1)
def decoder_inverts_16_bit_white_is_zero() -> bool:
    """Whether this OpenCV gives a 16-bit white-is-zero gray TIFF inverted (0 black), as it does an 8-bit one: a
    1 px file of stored 0 (white) decoded (OpenCV 5.1 gives it as stored, 0)."""
    import cv2

    entries = [(256, SHORT, 1), (257, SHORT, 1), (258, SHORT, 16), (259, SHORT, 1), (262, SHORT, 0), (273, LONG, 8),
               (277, SHORT, 1), (278, SHORT, 1), (279, LONG, 2)]
    ifd = struct.pack("<H", len(entries)) + b"".join(
        struct.pack("<HHIHH", tag, kind, 1, v, 0) if kind == SHORT else struct.pack("<HHII", tag, kind, 1, v)
        for tag, kind, v in entries) + struct.pack("<I", 0)
    img = cv2.imdecode(np.frombuffer(b"II*\0" + struct.pack("<I", 10) + b"\0\0" + ifd, np.uint8), cv2.IMREAD_UNCHANGED)
    return img is not None and int(img.reshape(-1)[0]) != 0


def black_is_zero(img: np.ndarray | None, data: bytes) -> np.ndarray | None:
    """OpenCV's decode img of the file data with 0 black: a 16-bit white-is-zero gray TIFF (white_is_zero_16_bit)
    inverted (65535 - v, the TIFF's full scale) where this OpenCV gives it as stored (an 8-bit one it inverts
    itself); img as it is otherwise."""
    if (img is None or img.ndim != 2 or img.dtype != np.uint16 or not white_is_zero_16_bit(data)
            or decoder_inverts_16_bit_white_is_zero()):
        return img
    return np.iinfo(np.uint16).max - img


def over_black(img: np.ndarray, is_premultiplied: bool = False) -> np.ndarray:
    """Colour or gray with alpha as its last channel (BGRA; gray+alpha), uint8 or uint16, composited over black:
    each colour value x alpha / full scale, rounded (as it is when premultiplied already); alpha dropped. A fully
    opaque alpha leaves the colour's values as they are. Returns (H, W, 3) or (H, W)."""
    colour, alpha = img[..., :-1], img[..., -1:]
    if not is_premultiplied:
        top = np.iinfo(img.dtype).max
        colour = ((colour.astype(np.uint32) * alpha + top // 2) // top).astype(img.dtype)
    return colour[..., 0] if colour.shape[2] == 1 else colour


def png_gray_key(data: bytes) -> int | None:
    """A gray PNG's transparent value (colour type 0 with a tRNS chunk) at the depth OpenCV gives its pixels (1-, 2-
    and 4-bit gray scaled to 8 bits); None for any other file. OpenCV gives such a PNG as one channel and drops the
    key; a palette's or an RGB PNG's tRNS it gives as an alpha channel (composited by over_black)."""
    if data[:8] != PNG_SIGNATURE or data[12:16] != b"IHDR" or len(data) < 26 or data[25] != 0:
        return None
    top = (1 << data[24]) - 1
    i = 8
    while i + 8 <= len(data) and data[i + 4:i + 8] not in (b"IDAT", b"IEND"):
        size = int.from_bytes(data[i:i + 4], "big")
        if data[i + 4:i + 8] == b"tRNS" and size >= 2 and i + 10 <= len(data):
            key = int.from_bytes(data[i + 8:i + 10], "big") & top  # as libpng masks it
            return key if top >= 255 else key * (255 // top)
        i += 12 + size
    return None


def keyed_over_black(img: np.ndarray | None, key: int | None) -> np.ndarray | None:
    """A gray frame whose pixels of value key (png_gray_key) are transparent, composited over black like an alpha
    of 0: those 0, the rest as they are; img as it is without a key."""
    if key is None or img is None or img.ndim != 2:
        return img
    return np.where(img == key, np.zeros((), img.dtype), img)


def orientation_caution(source: str, turned: list[tuple[str, int]], frames: int,
                        size_px: tuple[int, int]) -> list[str]:
    """What to warn of, once per source, when frames carry an EXIF Orientation other than 1 (turned: (file, its
    Orientation) each): their pixels are used as stored, so the intrinsics must describe those; [] when none."""
    if not turned:
        return []
    path, value = turned[0]
    others = sorted({v for _, v in turned} - {value})
    also = f"; others {', '.join(map(str, others))}" if others else ""
    return [f"source {source!r}: {len(turned)} of the {frames} frames carry an EXIF Orientation other than 1 "
            f"({path!r}: Orientation {value}, which viewers show {SHOWN[value]}{also}): their pixels are used as "
            f"stored ({size_px[0]} x {size_px[1]} px), not turned as a viewer shows them, so the camera's "
            "intrinsics (`camera`: fx, fy, cx, cy, width, height) must describe the stored pixels"]
