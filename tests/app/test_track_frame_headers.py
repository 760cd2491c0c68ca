"""A user's frames whose files say more than their pixels (pipelines/runs/frame_pixels.py): an EXIF Orientation
(a phone's JPEG, a TIFF) is not applied, the pixels are used as stored and the source is warned of once, naming
the file and the value (OpenCV's JPEG reader ignored the tag without a word; its TIFF reader turned the pixels by
it); colour with alpha is composited over black (a transparent background read as the white its pixels stored),
for 8- and 16-bit files, gray+alpha too, and a fully opaque alpha gives the bytes it gave before. Every file is
written here, its EXIF by hand; nothing here tracks."""

import struct
import warnings
import zlib

import numpy as np
import pytest

from envisat_pose.app.cli import main
from envisat_pose.config_errors import InputError
from envisat_pose.pipelines.runs.frame_pixels import as_stored
from envisat_pose.pipelines.runs.frames import open_source, read_gray, scan_source, to_gray

H, W = 24, 40  # stored: wider than high, so a turn by 90 deg shows in the shape


def stored_frame(seed=0):
    """A gray frame whose left quarter is white: any turn or mirror moves it."""
    img = np.random.default_rng(seed).integers(0, 100, (H, W), dtype=np.uint8)
    img[:, : W // 4] = 255
    return img


def tiff_ifd(order, entries, data_end):
    """A TIFF header whose first directory holds SHORT/LONG entries (tag, type, value), after data_end bytes of
    data."""
    out = (b"II" if order == "<" else b"MM") + struct.pack(order + "HI", 42, 8 + data_end)
    ifd = struct.pack(order + "H", len(entries))
    for tag, kind, value in sorted(entries):
        packed = struct.pack(order + "HH", value, 0) if kind == 3 else struct.pack(order + "I", value)
        ifd += struct.pack(order + "HHI", tag, kind, 1) + packed
    return out, ifd + struct.pack(order + "I", 0)


def exif_jpeg(img, orientation, order="<"):
    """img as a JPEG whose APP1 Exif segment (written here, after OpenCV's APP0) holds the Orientation."""
    import cv2

    ok, jpg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 100])
    jpg = jpg.tobytes()
    head, ifd = tiff_ifd(order, [(274, 3, orientation)], 0)
    body = b"Exif\0\0" + head + ifd
    app0_end = 4 + int.from_bytes(jpg[4:6], "big")  # SOI, APP0 (JFIF)
    return jpg[:app0_end] + b"\xff\xe1" + struct.pack(">H", len(body) + 2) + body + jpg[app0_end:]


def tiff_file(pixels, orientation=None, extra_samples=None, order="<", photometric=None):
    """An uncompressed one-strip TIFF of pixels ((H, W) gray, (H, W, 3|4) RGB(A), 8 or 16 bits), written here;
    photometric: its Photometric (default 1, black is zero, for gray; 2 for colour)."""
    h, w = pixels.shape[:2]
    spp = 1 if pixels.ndim == 2 else pixels.shape[2]
    data = pixels.astype(pixels.dtype.newbyteorder(order)).tobytes()
    photometric = photometric if photometric is not None else 1 if spp < 3 else 2
    entries = [(256, 3, w), (257, 3, h), (258, 3, pixels.dtype.itemsize * 8), (259, 3, 1), (262, 3, photometric),
               (273, 4, 8), (277, 3, spp), (278, 3, h), (279, 4, len(data))]
    entries += [(274, 3, orientation)] if orientation else []
    entries += [(338, 3, extra_samples)] if extra_samples is not None else []
    head, ifd = tiff_ifd(order, entries, len(data))
    return head + data + ifd


def gray_alpha_png(gray, alpha):
    """A PNG of colour type 4 (gray + alpha, 8-bit), written here: OpenCV writes none."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    rows = b"".join(b"\0" + row.tobytes() for row in np.dstack([gray, alpha]))
    ihdr = struct.pack(">IIBBBBB", gray.shape[1], gray.shape[0], 8, 4, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b"")


def orientation_warnings(source):
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        scan_source(source)
    return [str(w.message) for w in seen if "Orientation" in str(w.message)]


# ---------------------------------------------------------------------------------------------------------
# EXIF Orientation


def test_the_orientation_is_read_from_a_jpeg_a_tiff_a_png_and_a_webp():
    img = stored_frame()
    for order in "<>":
        for value in (1, 3, 6, 8):
            data, found, _ = as_stored(exif_jpeg(img, value, order))
            assert found == value and as_stored(data)[1] == 1  # set to 1 in what the decoder gets
    assert as_stored(tiff_file(img, 6, order=">"))[1] == 6
    head, ifd = tiff_ifd("<", [(274, 3, 5)], 0)
    png = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", len(head + ifd)) + b"eXIf" + head + ifd + b"\0" * 4
    assert as_stored(png)[1] == 5
    webp = b"RIFF\0\0\0\0WEBP" + b"EXIF" + struct.pack("<I", len(head + ifd) + 6) + b"Exif\0\0" + head + ifd
    assert as_stored(webp)[1] == 5
    jpg = exif_jpeg(img, 6)
    for damaged in (jpg[:30], jpg[:24] + b"\xff" * 8 + jpg[32:], b"II*\0\xff\xff\xff\xff"):  # no crash: no turn
        assert as_stored(damaged)[1] in (1, 6)
    assert as_stored(exif_jpeg(img, 0))[1] == 1 and as_stored(exif_jpeg(img, 9))[1] == 1  # not a turn: ignored


def test_a_turned_jpeg_is_used_as_stored_and_warned_of_once(tmp_path):
    """Orientation 6 (a phone held upright): the pixels as stored, 40 x 24 px, and one warning for the source
    naming the first file, its value and how viewers show it; none for Orientation 1 or no EXIF."""
    img = stored_frame()
    src = tmp_path / "phone"
    src.mkdir()
    for i in range(3):
        (src / f"img_{i:04d}.jpg").write_bytes(exif_jpeg(img, 6, "<>"[i % 2]))
    frame = read_gray(str(src / "img_0000.jpg"))
    assert frame.shape == (H, W) and frame[:, : W // 4].min() > 200 and frame[:, W // 2:].max() < 150
    source = open_source(str(src), 1.0)
    said = orientation_warnings(source)
    assert len(said) == 1, said
    assert f"{str(src / 'img_0000.jpg')!r}: Orientation 6, which viewers show turned 90 deg clockwise" in said[0]
    assert "3 of the 3 frames" in said[0] and f"used as stored ({W} x {H} px)" in said[0]
    assert source.size_px == (W, H)
    plain = tmp_path / "plain"
    plain.mkdir()
    import cv2

    (plain / "a_0.jpg").write_bytes(exif_jpeg(img, 1))
    assert cv2.imwrite(str(plain / "a_1.jpg"), img)  # no EXIF
    assert orientation_warnings(open_source(str(plain), 1.0)) == []


def test_a_turned_tiff_is_used_as_stored(tmp_path):
    """OpenCV's TIFF reader turned the pixels by the tag (40 x 24 px read as 24 x 40); now they are as stored,
    8- and 16-bit, and the source is warned of."""
    img = stored_frame()
    src = tmp_path / "tiffs"
    src.mkdir()
    for i, (value, pixels) in enumerate([(6, img), (3, img), (8, img.astype(np.uint16) * 64)]):
        path = src / f"f_{i}.tif" if pixels.dtype == np.uint8 else tmp_path / "wide.tif"
        path.write_bytes(tiff_file(pixels, value, order="<>"[i % 2]))
        frame = read_gray(str(path))
        assert frame.shape == (H, W) and frame.dtype == pixels.dtype
        np.testing.assert_array_equal(frame, pixels)
    said = orientation_warnings(open_source(str(src), 1.0))
    assert len(said) == 1 and "2 of the 2 frames" in said[0] and "Orientation 6" in said[0], said
    assert "others 3" in said[0]


def test_the_verb_names_its_flags_in_the_warning(tmp_path, capsys):
    src = tmp_path / "phone"
    src.mkdir()
    for i in range(3):
        (src / f"img_{i}.jpg").write_bytes(exif_jpeg(stored_frame(i), 8))
    cfg = tmp_path / "fast.toml"
    cfg.write_text("[tracker.acquire]\nframes = 3\n")
    code = main(["track", "--images", str(src), "--rate-hz", "1", "--config", str(cfg), "--out",
                 str(tmp_path / "never"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 2, err  # the warning, then the frames are not the default camera's size
    assert err[0].startswith("envisat track: warning: --images") and "Orientation 8" in err[0]
    assert "--camera" in err[0] and "`" not in err[0]


# ---------------------------------------------------------------------------------------------------------
# Alpha


def rgba_frame(dtype):
    """BGRA: a white background of alpha 0, an opaque square, a half-transparent stripe."""
    top = np.iinfo(dtype).max
    img = np.zeros((H, W, 4), dtype)
    img[...] = top
    img[..., 3] = 0
    img[4:12, 4:12] = np.array([50, 100, 150, 255], np.float64) * top / 255
    img[16:20, :] = [top, top, top, top // 2 + 1]
    return img


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_a_transparent_background_is_black(tmp_path, dtype):
    import cv2

    img = rgba_frame(dtype)
    top = np.iinfo(dtype).max
    path = str(tmp_path / "rgba.png")
    assert cv2.imwrite(path, img)
    gray = read_gray(path)
    assert gray.dtype == dtype
    assert gray[0, 0] == 0 and gray[22, 30] == 0  # was the white the transparent pixels store
    square = cv2.cvtColor(np.ascontiguousarray(img[4:12, 4:12, :3]), cv2.COLOR_BGR2GRAY)
    np.testing.assert_array_equal(gray[4:12, 4:12], square)  # opaque: as it was
    half = round(top * (top // 2 + 1) / top)
    assert np.all(gray[16:20] == half)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_a_fully_opaque_alpha_gives_the_bytes_it_gave(tmp_path, dtype):
    import cv2

    top = np.iinfo(dtype).max
    img = np.random.default_rng(3).integers(0, top, (H, W, 4), dtype=dtype, endpoint=True)
    img[..., 3] = top
    path = str(tmp_path / "opaque.png")
    assert cv2.imwrite(path, img)
    before = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)  # what to_gray gave before alpha was composited
    assert read_gray(path).tobytes() == before.tobytes()


def test_gray_and_alpha_are_composited_over_black(tmp_path):
    """A gray+alpha PNG (OpenCV gives it as BGRA) and a gray+alpha array (two channels, which cvtColor refused
    with an OpenCV error)."""
    gray = np.full((H, W), 200, np.uint8)
    alpha = np.zeros((H, W), np.uint8)
    alpha[:, : W // 2] = 255
    alpha[:, W // 2: W // 2 + 4] = 64
    path = tmp_path / "ga.png"
    path.write_bytes(gray_alpha_png(gray, alpha))
    for out in (read_gray(str(path)), to_gray(np.dstack([gray, alpha]), "ga")):
        assert out.shape == (H, W) and out.dtype == np.uint8
        assert out[0, 0] == 200 and out[0, W // 2] == round(200 * 64 / 255) and out[0, -1] == 0


def test_a_16_bit_gray_alpha_png_is_its_8_bit_equivalent_within_rounding(tmp_path):
    """A PNG of colour type 4 at 16 bits (gray and alpha, big-endian: OpenCV writes none) reads as its 8-bit twin
    (every value x 257) does: composited over black at 16 bits, within half an 8-bit level plus the 16-bit rounding,
    and the frames `envisat track` uses (scaled to 8 bits from the detected 16 bits) within one level; a fully
    opaque or fully transparent pixel exactly."""
    rng = np.random.default_rng(5)
    gray8, alpha8 = rng.integers(0, 256, (2, H, W), dtype=np.uint8)
    alpha8[:4], alpha8[4:8] = 255, 0
    gray8[0, 0] = 255  # the 16-bit frames' full scale: their bit depth detected as 16
    for bits, (g, a) in ((8, (gray8, alpha8)), (16, (gray8.astype(">u2") * 257, alpha8.astype(">u2") * 257))):
        (tmp_path / f"f{bits}").mkdir()
        rows = [r.tobytes() for r in np.dstack([g, a])]
        (tmp_path / f"f{bits}" / "000.png").write_bytes(png_file(W, H, bits, 4, rows))
    eight, sixteen = read_gray(str(tmp_path / "f8" / "000.png")), read_gray(str(tmp_path / "f16" / "000.png"))
    assert eight.dtype == np.uint8 and sixteen.dtype == np.uint16 and sixteen.shape == (H, W)
    assert np.abs(sixteen / 257 - gray8.astype(float) * alpha8 / 255).max() <= 0.5 / 257 + 1e-9
    assert np.abs(sixteen / 257 - eight).max() <= 0.5 + 0.5 / 257 + 1e-9
    np.testing.assert_array_equal(sixteen[:8], eight[:8].astype(np.uint16) * 257)  # opaque, then transparent: 0
    frames = []
    for bits in (8, 16):
        source = open_source(str(tmp_path / f"f{bits}"), 1.0)
        scan_source(source)
        frames.append(next(source.frames())[1])
    assert source.bit_depth == 16 and frames[1].dtype == np.uint8
    assert np.abs(frames[1].astype(int) - frames[0]).max() <= 1
    np.testing.assert_array_equal(frames[1][:8], frames[0][:8])


def test_a_tiffs_premultiplied_colour_is_not_multiplied_twice(tmp_path):
    """An 8-bit TIFF's unassociated alpha (ExtraSamples 2) comes premultiplied from OpenCV's reader (libtiff's
    RGBA), associated alpha (1) is stored so; a 16-bit TIFF's unassociated alpha comes as stored."""
    for dtype, extra, want in ((np.uint8, 2, 100), (np.uint8, 1, 200), (np.uint16, 2, 100 * 257),
                               (np.uint16, 1, 200 * 257)):
        scale = 1 if dtype == np.uint8 else 257
        rgba = np.zeros((H, W, 4), dtype)
        rgba[...] = [200 * scale, 200 * scale, 200 * scale, 128 * scale]
        path = tmp_path / f"{np.dtype(dtype).name}_{extra}.tif"
        path.write_bytes(tiff_file(rgba, extra_samples=extra))
        gray = read_gray(str(path))
        assert abs(int(gray[0, 0]) - want) <= scale, (dtype, extra, gray[0, 0])


# ---------------------------------------------------------------------------------------------------------
# Gray+alpha TIFFs: OpenCV gave them as one 8-bit channel, the alpha dropped (a 16-bit one at 8 bits too)


def tiff_bytes(order, entries, chunks, tiled=False):
    """A TIFF of one directory: entries (tag, type 3|4, [values]), the strips' or tiles' bytes (chunks) first, their
    offsets and byte counts filled in; values over 4 bytes after them."""
    offsets, at = [], 8
    for c in chunks:
        offsets.append(at)
        at += len(c)
    body = b"".join(chunks) + b"\0" * (at & 1)
    at += at & 1
    entries = sorted(entries + [(324 if tiled else 273, 4, offsets),
                                (325 if tiled else 279, 4, [len(c) for c in chunks])])
    values, ifd = b"", b""
    for tag, kind, vals in entries:
        packed = struct.pack(order + ("H" if kind == 3 else "I") * len(vals), *vals)
        if len(packed) > 4:
            packed, values = struct.pack(order + "I", at + len(values)), values + packed
        ifd += struct.pack(order + "HHI", tag, kind, len(vals)) + packed.ljust(4, b"\0")
    head = (b"II" if order == "<" else b"MM") + struct.pack(order + "HI", 42, at + len(values))
    return head + body + values + struct.pack(order + "H", len(entries)) + ifd + struct.pack(order + "I", 0)


def gray_alpha_tiff_file(ga, extra=2, order="<", white_is_zero=False, tile=None, deflate=False, planar=1):
    """ga (H, W, 2) gray+alpha, 8 or 16 bits, as libtiff writes it: BitsPerSample twice, ExtraSamples `extra`
    (None: none), strips of 16 rows or tiles of `tile` px; deflate: Deflate with horizontal differencing by pixel
    (Predictor 2, as libtiff and most tools write it)."""
    h, w, _ = ga.shape
    stored = ga.astype(ga.dtype.newbyteorder(order))

    def encode(block):
        if not deflate:
            return block.tobytes()
        diff = block.copy()
        diff[:, 1:] = block[:, 1:] - block[:, :-1]  # wraps, as the predictor's sums do
        return zlib.compress(diff.tobytes())

    if planar == 2:
        chunks = [stored[..., k].tobytes() for k in range(2)]
    elif tile:
        padded = np.zeros((-(-h // tile) * tile, -(-w // tile) * tile, 2), stored.dtype)
        padded[:h, :w] = stored
        chunks = [encode(padded[y:y + tile, x:x + tile]) for y in range(0, h, tile) for x in range(0, w, tile)]
    else:
        chunks = [encode(stored[y:y + 16]) for y in range(0, h, 16)]
    bits = ga.dtype.itemsize * 8
    entries = [(256, 3, [w]), (257, 3, [h]), (258, 3, [bits, bits]), (259, 3, [8 if deflate else 1]),
               (262, 3, [0 if white_is_zero else 1]), (277, 3, [2]), (284, 3, [planar])]
    entries += [(338, 3, [extra])] if extra is not None else []
    entries += [(317, 3, [2])] if deflate else []
    entries += [(322, 3, [tile]), (323, 3, [tile])] if tile else [(278, 3, [h if planar == 2 else 16])]
    return tiff_bytes(order, entries, chunks, tiled=bool(tile) and planar == 1)


def composited(gray, alpha, dtype):
    """gray over black by alpha, rounded: what every alpha path gives."""
    top = np.iinfo(dtype).max
    return ((gray.astype(np.uint64) * alpha + top // 2) // top).astype(dtype)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_a_gray_alpha_tiff_is_composited_over_black_at_its_depth(tmp_path, dtype):
    """Gray 200 (x 257 at 16 bits): opaque on the left, alpha 64 in a stripe, transparent on the right; its
    unassociated (2), unspecified (0) or missing ExtraSamples taken as alpha, as for BGRA; associated alpha (1)
    stored premultiplied; both byte orders. OpenCV gave 200 everywhere, at 8 bits."""
    top = np.iinfo(dtype).max
    scale = top // 255
    alpha = np.zeros((H, W), dtype)
    alpha[:, : W // 2] = top
    alpha[:, W // 2: W // 2 + 4] = 64 * scale
    gray = np.full((H, W), 200 * scale, dtype)
    want = composited(gray, alpha, dtype)
    for extra, order in ((2, "<"), (2, ">"), (0, "<"), (None, ">"), (1, "<"), (1, ">")):
        stored = want if extra == 1 else gray
        path = tmp_path / f"ga_{extra}_{order == '<'}.tif"
        path.write_bytes(gray_alpha_tiff_file(np.dstack([stored, alpha]), extra, order))
        out = read_gray(str(path))
        assert out.dtype == dtype and out.shape == (H, W), (extra, order, out.dtype)
        np.testing.assert_array_equal(out, want, err_msg=f"ExtraSamples {extra}, {order}")
        assert out[0, 0] == 200 * scale and out[0, -1] == 0


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_a_compressed_gray_alpha_tiff_in_strips_or_tiles(tmp_path, dtype):
    """Deflate with horizontal differencing (undone by pixel, not by sample), in strips and in 16-px tiles that
    overhang the image; a MinIsWhite one's gray inverted; random pixels (seed 5)."""
    top = np.iinfo(dtype).max
    rng = np.random.default_rng(5)
    ga = rng.integers(0, top, (H, W, 2), dtype=dtype, endpoint=True)
    ga[:, :4, 1] = top
    ga[:, -4:, 1] = 0
    for tile, white_is_zero, order in ((None, False, "<"), (16, False, ">"), (16, True, "<"), (None, True, ">")):
        path = tmp_path / f"c_{tile}_{white_is_zero}_{order == '<'}.tif"
        path.write_bytes(gray_alpha_tiff_file(ga, 2, order, white_is_zero, tile, deflate=True))
        gray = top - ga[..., 0] if white_is_zero else ga[..., 0]
        out = read_gray(str(path))
        assert out.dtype == dtype
        np.testing.assert_array_equal(out, composited(gray, ga[..., 1], dtype), err_msg=f"{tile} {white_is_zero}")


def test_a_gray_alpha_tiff_in_separate_planes_is_refused(tmp_path):
    """OpenCV gives such a file's gray alone: one line naming the file and the tag, not a frame without its alpha."""
    ga = np.dstack([np.full((H, W), 200, np.uint8), np.zeros((H, W), np.uint8)])
    path = tmp_path / "planes.tif"
    path.write_bytes(gray_alpha_tiff_file(ga, planar=2))
    with pytest.raises(InputError, match=r"planes\.tif: a gray\+alpha TIFF .*PlanarConfiguration 2"):
        read_gray(str(path))


# ---------------------------------------------------------------------------------------------------------
# PNG transparency (tRNS): a gray PNG's transparent value was dropped by OpenCV; a palette's or an RGB PNG's
# comes from OpenCV as an alpha channel (pinned here)


def png_file(width, height, bits, colour, rows, *chunks):
    """A PNG of colour type `colour` whose rows are given as bytes, with `chunks` ((kind, data)) before its IDAT."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, bits, colour, 0, 0, 0)
    idat = zlib.compress(b"".join(b"\0" + r for r in rows))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + b"".join(chunk(k, d) for k, d in chunks)
            + chunk(b"IDAT", idat) + chunk(b"IEND", b""))


def test_a_gray_pngs_transparent_value_is_black(tmp_path):
    """A white background keyed transparent (tRNS), 8- and 16-bit, and 4- and 1-bit gray (scaled to 8 bits by the
    decoder): those pixels 0, the others as they were; OpenCV gave the white."""
    img = stored_frame()  # its left quarter white (255): the key
    cases = [(8, img, 255, img), (16, img.astype(">u2") * 257, 65535, img.astype(np.uint16) * 257)]
    four = (img // 17).astype(np.uint8)  # 0-15, the white 15
    cases.append((4, (four[:, 0::2] << 4) | four[:, 1::2], 15, four * 17))
    one = (img == 255).astype(np.uint8)
    cases.append((1, np.packbits(one, axis=1), 1, one * 255))
    for bits, rows, key, decoded in cases:
        path = tmp_path / f"key_{bits}.png"
        path.write_bytes(png_file(W, H, bits, 0, [r.tobytes() for r in rows], (b"tRNS", struct.pack(">H", key))))
        out = read_gray(str(path))
        assert out.dtype == decoded.dtype, bits
        want = np.where(img == 255, 0, decoded)
        np.testing.assert_array_equal(out, want, err_msg=f"{bits}-bit")
    path = tmp_path / "plain.png"  # no tRNS: as it was
    path.write_bytes(png_file(W, H, 8, 0, [r.tobytes() for r in img]))
    np.testing.assert_array_equal(read_gray(str(path)), img)


def test_a_palette_or_rgb_pngs_transparency_is_composited_as_alpha(tmp_path):
    """OpenCV gives these four channels (IMREAD_UNCHANGED): a palette's tRNS alphas (0 and 128 here) and an RGB
    PNG's transparent colour (white), 8- and 16-bit; over black like any alpha."""
    import cv2

    index = np.zeros((H, W), np.uint8)  # 0: white, transparent; 1: gray 200, alpha 128; 2: opaque colour
    index[:, W // 2:] = 1
    index[:4] = 2
    plte = bytes([255, 255, 255, 200, 200, 200, 50, 100, 150])
    path = tmp_path / "palette.png"
    path.write_bytes(png_file(W, H, 8, 3, [r.tobytes() for r in index], (b"PLTE", plte), (b"tRNS", bytes([0, 128]))))
    out = read_gray(str(path))
    colour = int(cv2.cvtColor(np.array([[[150, 100, 50]]], np.uint8), cv2.COLOR_BGR2GRAY)[0, 0])
    assert out[10, 0] == 0 and out[10, -1] == round(200 * 128 / 255) and out[0, 0] == colour
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[...] = 255
    rgb[:, W // 2:] = [50, 100, 150]
    for bits, rows, key in ((8, rgb, 255), (16, rgb.astype(">u2") * 257, 65535)):
        path = tmp_path / f"rgb_{bits}.png"
        path.write_bytes(png_file(W, H, bits, 2, [r.tobytes() for r in rows],
                                  (b"tRNS", struct.pack(">3H", *[key] * 3))))
        out = read_gray(str(path))
        bgr = np.array([[[150, 100, 50]]], out.dtype) * (1 if bits == 8 else 257)
        assert out.dtype == (np.uint8 if bits == 8 else np.uint16)
        assert out[0, 0] == 0 and out[0, -1] == cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)[0, 0]


def test_a_white_is_zero_gray_tiff_is_one_picture_at_8_and_16_bits(tmp_path, monkeypatch):
    """A gray TIFF stored white-is-zero (Photometric 0): OpenCV gave an 8-bit one inverted (0 black) and a 16-bit
    one as stored (0 white: the target black on white, a negative of the scene); now both come with 0 black, the
    16-bit one at its full scale, either byte order; black-is-zero files as they were. An OpenCV that inverted
    16-bit ones itself is not inverted twice."""
    from envisat_pose.pipelines.runs import frame_pixels
    from envisat_pose.pipelines.runs.frames import to_u8

    stored8 = stored_frame()  # as stored: 255 is black in a white-is-zero file
    stored16 = stored8.astype(np.uint16) * 257
    scene8 = 255 - stored8
    for i, order in enumerate("<>"):
        (tmp_path / f"w8{order}.tif").write_bytes(tiff_file(stored8, order=order, photometric=0))
        (tmp_path / f"w16{order}.tif").write_bytes(tiff_file(stored16, order=order, photometric=0))
        (tmp_path / f"b16{order}.tif").write_bytes(tiff_file(stored16, order=order))
        assert np.array_equal(read_gray(str(tmp_path / f"w8{order}.tif")), scene8)
        wiz16 = read_gray(str(tmp_path / f"w16{order}.tif"))
        assert wiz16.dtype == np.uint16 and np.array_equal(wiz16, 65535 - stored16), order
        assert np.array_equal(to_u8(wiz16, 16), scene8)
        assert np.array_equal(read_gray(str(tmp_path / f"b16{order}.tif")), stored16)
    monkeypatch.setattr(frame_pixels, "decoder_inverts_16_bit_white_is_zero", lambda: True)
    assert np.array_equal(read_gray(str(tmp_path / "w16<.tif")), stored16)  # left as the decoder gave it
