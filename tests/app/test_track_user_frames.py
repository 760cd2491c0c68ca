"""A user's own frames as they come (issue: frames brought to `envisat track`): a timestamps CSV from a
spreadsheet (byte-order mark, spaces in the header), a short row, one file given two times, a time that is not
finite named at its file; one frame saved in two formats; numbered names that skip numbers under --rate-hz
warned of once the frames pass, the warning's names as flags; one image file given for the folder; a video cut short; a camera file
with its keys under a table, a TOML error named as the camera; what Tracker.step says of a colour or 16-bit
frame. Small synthetic frames: nothing here tracks."""

import os

import numpy as np
import pytest

from envisat_pose.app.cli import main
from envisat_pose.config import InputError
from envisat_pose.pipelines.runs.frame_names import numbering_gap, read_timestamps, sorted_frames
from envisat_pose.pipelines.runs.frames import open_source, scan_source

SIDE = 32


def frames(folder, names):
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for n in names:
        assert cv2.imwrite(str(folder / n), rng.integers(0, 256, (SIDE, SIDE), dtype=np.uint8))
    return folder


NAMES = [f"img_{i:04d}.png" for i in range(4)]


def csv_times(tmp_path, text):
    path = tmp_path / "times.csv"
    path.write_bytes(text.encode("utf-8"))
    return str(path)


def test_a_spreadsheets_csv_is_read(tmp_path):
    """Excel's "CSV UTF-8" starts with a byte-order mark; a header typed as 'file, t_s' has a space: both read."""
    rows = "".join(f"{n}, {i * 0.5}\n" for i, n in enumerate(NAMES))
    for head in ("\ufefffile,t_s\n", "file, t_s\n", "\ufeff t_s , file\n"):
        body = rows if "file," in head else "".join(f"{i * 0.5},{n}\n" for i, n in enumerate(NAMES))
        np.testing.assert_allclose(read_timestamps(csv_times(tmp_path, head + body), NAMES), [0, 0.5, 1, 1.5])


def test_bad_rows_are_one_line_naming_the_line_or_the_file(tmp_path):
    rows = "".join(f"{i},{n}\n" for i, n in enumerate(NAMES))
    with pytest.raises(InputError, match=r"line 6: '99': expected a file and a time"):  # was an AttributeError
        read_timestamps(csv_times(tmp_path, "t_s,file\n" + rows + "99\n"), NAMES)
    rows = "".join(f"{n},{i}\n" for i, n in enumerate(NAMES))
    with pytest.raises(InputError, match=r"line 6: 'img_0002.png' at t = 2.5 s, but t = 2.0 s"):  # was taken
        read_timestamps(csv_times(tmp_path, "file,t_s\n" + rows + "img_0002.png,2.5\n"), NAMES)
    last_inf = "".join(f"{n},{i if i < 3 else 'inf'}\n" for i, n in enumerate(NAMES))
    with pytest.raises(InputError, match=r"img_0003.png at t = inf s: expected a finite time"):  # named img_0001
        read_timestamps(csv_times(tmp_path, "file,t_s\n" + last_inf), NAMES)
    with pytest.raises(InputError, match=r"header 'file;t_s'"):
        read_timestamps(csv_times(tmp_path, "file;t_s\n"), NAMES)


def test_one_frame_saved_in_two_formats_is_refused(tmp_path):
    """img_0001.png and img_0001.jpg are the same frame twice: tracked both, the sequence was twice as long."""
    src = frames(tmp_path / "both", NAMES + [n.replace(".png", ".jpg") for n in NAMES])
    with pytest.raises(InputError, match=r"'img_0000.jpg' and 'img_0000.png' have the same frame number"):
        sorted_frames(str(src), os.listdir(src))
    with pytest.raises(InputError, match="same frame number"):
        open_source(str(src), 1.0)


def test_numbered_names_that_skip_are_warned_of_under_a_rate(tmp_path):
    gappy = [f"frame_{i}.png" for i in (0, 1, 2, 3, 9, 10, 11)]
    assert numbering_gap(gappy) == ("frame_3.png", "frame_9.png", 6, 1)
    assert numbering_gap([f"f_{i}.png" for i in range(0, 50, 10)]) is None  # every 10th frame: one step
    assert numbering_gap(["a_1.png", "b_2.png", "c_9.png"]) is None  # no one pattern
    src = frames(tmp_path / "gappy", gappy)
    source = open_source(str(src), 1.0)
    with pytest.warns(UserWarning, match=r"skip from 'frame_3.png' to 'frame_9.png'.*`timestamps`"):
        scan_source(source)  # once the frames pass: a refusal stays one line
    np.testing.assert_allclose(source.t_s, np.arange(7.0))  # by position, as documented
    times = csv_times(tmp_path, "file,t_s\n" + "".join(f"{n},{n[6:-4]}\n" for n in gappy))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        source = open_source(str(src), timestamps=times)
        scan_source(source)
        np.testing.assert_allclose(source.t_s, [0, 1, 2, 3, 9, 10, 11])


def test_the_verb_warns_with_its_flags(tmp_path, capsys):
    """The warning reaches the terminal as one line naming --images and --timestamps (the library's `names` as the
    verb's flags, as its errors are); then the frames are too few for the cold start."""
    src = frames(tmp_path / "gappy", [f"frame_{i}.png" for i in (0, 1, 2, 3, 9, 10, 11)])
    cfg = tmp_path / "fast.toml"
    cfg.write_text("[tracker.acquire]\nframes = 3\n")
    code = main(["track", "--images", str(src), "--rate-hz", "1", "--config", str(cfg), "--out",
                 str(tmp_path / "never"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 2, err
    assert err[0].startswith("envisat track: warning: --images") and "--timestamps" in err[0] and "`" not in err[0]
    assert f"frames of {SIDE} x {SIDE} px, not the default camera's" in err[1]
    # a refused input is one line: too few frames for the cold start, no warning before it
    code = main(["track", "--images", str(src), "--rate-hz", "1", "--out", str(tmp_path / "never"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "7 frame(s)" in err[0], err


def test_one_image_file_is_refused_with_its_folder(tmp_path):
    """Given for the folder, one PNG was opened as a one-frame video."""
    src = frames(tmp_path / "seq", NAMES)
    with pytest.raises(InputError, match=r"one image file; expected the folder of the sequence's frames"):
        open_source(str(src / "img_0001.png"), 1.0)


def test_a_video_cut_short_is_warned_of(tmp_path):
    import cv2

    video = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 1.0, (64, 64), isColor=True)
    rng = np.random.default_rng(1)
    for _ in range(20):
        w.write(rng.integers(0, 256, (64, 64, 3), dtype=np.uint8))
    w.release()
    data = video.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: len(data) // 2])
    source = open_source(str(cut), 0.0)
    with pytest.warns(UserWarning, match=r"of the 20 frames the video's header counts can be read"):
        scan_source(source)
    assert 0 < len(source.t_s) < 20
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        source = open_source(str(video), 0.0)
        scan_source(source)
        assert len(source.t_s) == 20


def test_camera_files_as_people_write_them(tmp_path):
    from envisat_pose.pipelines.tracking.camera_file import camera_from_intrinsics

    keys = "fx = 100.0\nfy = 100.0\ncx = 16.0\ncy = 16.0\nwidth = 32\nheight = 32\n"
    cam = tmp_path / "cam.toml"
    cam.write_text("[camera]\n" + keys)
    with pytest.raises(InputError, match=r"no 'fx' .*under \[camera\]: expected at the file's top level"):
        camera_from_intrinsics(str(cam))
    cam.write_text(keys + "distortion = [true, false, false, false]\n")
    with pytest.raises(InputError, match="distortion"):
        camera_from_intrinsics(str(cam))
    cam.write_text(keys + "fx = \n")
    with pytest.raises(InputError, match=r"^camera '.*cam.toml' is not valid TOML"):  # not "config file"
        camera_from_intrinsics(str(cam))


def test_tracker_step_says_how_to_make_the_frame_it_takes():
    from envisat_pose.pipelines.tracking.tracker import frame_refusal

    assert "cv2.COLOR_BGR2GRAY" in frame_refusal(np.zeros((32, 32, 3), np.uint8), (32, 32))
    assert "to_u8" in frame_refusal(np.zeros((32, 32), np.uint16), (32, 32))
    assert "its own camera" in frame_refusal(np.zeros((16, 32), np.uint8), (32, 32))


def test_tracker_step_refusal_of_a_frame_with_one_channel_says_a_way_that_works():
    """An (H, W, 1) frame (a gray image kept with its channel axis, as from image[..., None] or some readers) was
    told to use cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), which OpenCV refuses for one channel; the way given
    makes the frame the tracker takes."""
    from envisat_pose.pipelines.tracking.tracker import frame_refusal

    for channels in (1, 2):
        image = np.arange(32 * 32 * channels, dtype=np.uint8).reshape(32, 32, channels)
        said = frame_refusal(image, (32, 32))
        assert "cvtColor" not in said and "image[..., 0]" in said
        assert image[..., 0].shape == (32, 32)
    said = frame_refusal(np.zeros((32, 32, 3), np.uint8), (32, 32))
    assert "cv2.COLOR_BGR2GRAY" in said and "cv2.COLOR_RGB2GRAY" in said  # OpenCV's order, and most arrays'


@pytest.mark.parametrize("ext", [".bmp", ".pgm", ".webp"])
def test_other_image_files_opencv_reads_are_frames(tmp_path, ext):
    """BMP, PGM/PPM and WebP frames (a lab camera's or a converter's output) were skipped without a word: a folder
    of them had 'no image files'. Read as PNGs are (lossless WebP: the same pixels)."""
    import cv2

    src = tmp_path / "seq"
    src.mkdir()
    rng = np.random.default_rng(3)
    want = [rng.integers(0, 256, (SIDE, SIDE), dtype=np.uint8) for _ in range(3)]
    for i, img in enumerate(want):
        ok, buf = cv2.imencode(ext, img, [cv2.IMWRITE_WEBP_QUALITY, 101] if ext == ".webp" else [])
        (src / f"f_{i}{ext}").write_bytes(buf.tobytes())
    source = open_source(str(src), 1.0)
    scan_source(source)
    assert source.names == [f"f_{i}{ext}" for i in range(3)]
    for (i, got), img in zip(source.frames(), want):
        np.testing.assert_array_equal(got, img)


def test_names_that_are_decimal_times_are_warned_of_under_a_rate(tmp_path):
    """t_12.5.png and t_12.25.png: natural order put 12.5 before 12.25 and tracked the frames out of time order under
    --rate-hz without a word. Names of as many decimals each sort in time order: nothing to say."""
    from envisat_pose.pipelines.runs.frame_names import decimal_names_caution

    src = frames(tmp_path / "dec", [f"t_{t}.png" for t in ("12.0", "12.25", "12.5", "12.75", "13.0")])
    source = open_source(str(src), 4.0)
    assert source.names[:3] == ["t_12.0.png", "t_12.5.png", "t_12.25.png"]  # the order a user did not mean
    with pytest.warns(UserWarning, match=r"decimal numbers of unequal decimals.*12\.5 before 12\.25.*`timestamps`"):
        scan_source(source)
    assert decimal_names_caution("x", [f"t_{t}.png" for t in ("12.00", "12.25", "12.50")]) is None
    assert decimal_names_caution("x", [f"img_{i:04d}.png" for i in range(3)]) is None


def test_a_run_that_never_tracked_says_so_without_claiming_more():
    """'nothing tracked (39 acquiring, 1 lost): the tracker never got past acquisition' read wrong beside a lost
    frame; the line says what is known, and where coasting rows hold estimates, that they do."""
    from envisat_pose.pipelines.runs.outputs import status_line

    line = status_line(40, {"acquiring": 39, "lost": 1}, None, "lost", None)
    assert "nothing tracked (39 acquiring, 1 lost): the tracker never claimed tracking" in line
    assert "holds no estimate" in line
    line = status_line(40, {"acquiring": 37, "coasting": 2, "lost": 1}, None, "lost", None)
    assert "only in its coasting rows" in line
    assert "refused" not in line
    # the tracker's own reason, where its last cold start was refused (Tracker.last_refusal)
    why = "the frames read a focal length 0.80 x the camera's (likelihood ratio 90 > 24 over 20 frames)"
    line = status_line(40, {"acquiring": 40}, None, "acquiring", None, why)
    assert line.endswith("holds no estimate (x_hat NaN, status per row); its last cold start was refused: " + why)
    tracked = status_line(40, {"acquiring": 20, "tracking": 20}, 20.0, "tracking", 0.2, why)
    assert "refused" not in tracked  # a run that tracked says how it tracked


def test_frames_of_an_image_type_not_read_are_named(tmp_path):
    """GIF, JPEG 2000, EXR, FITS or camera-raw files among the frames were left out without a word (the sequence
    lost those frames silently); a folder of nothing else said 'no image files' without naming them."""
    src = frames(tmp_path / "mixed", NAMES)
    for name in ("img_0004.gif", "img_0005.exr", "img_0006.fits", "img_0007.jp2"):
        (src / name).write_bytes(b"\0" * 16)
    (src / ".hidden.gif").write_bytes(b"\0")
    source = open_source(str(src), 1.0)
    with pytest.warns(UserWarning, match=r"4 file\(s\) of an image type .*\(\.exr, \.fits, \.gif, \.jp2: "
                                         r"'img_0004.gif', 'img_0005.exr', 'img_0006.fits' and 1 more\) are left out"):
        scan_source(source)
    assert source.names == NAMES
    only = tmp_path / "only"
    only.mkdir()
    (only / "a.gif").write_bytes(b"\0")
    with pytest.raises(InputError, match=r"no image files .*1 file\(s\) of an image type .*'a.gif'"):
        open_source(str(only), 1.0)


def test_a_rate_that_puts_frames_beyond_the_recordings_clock_is_refused(tmp_path):
    """--rate-hz 1e-12 (a rate in the wrong unit) tracked every frame, then the recording's int64-ns clock
    overflowed (a traceback after the work); refused before any frame is read, naming the rate."""
    src = frames(tmp_path / "seq", NAMES)
    with pytest.raises(InputError, match=r"rate_hz 1e-12: frame 3 .* beyond the recording's clock"):
        open_source(str(src), 1e-12)
    assert open_source(str(src), 1e-6).t_s[-1] == pytest.approx(3e6)  # slow, but on the clock


def test_timestamps_closer_than_the_physics_least_step_are_refused_naming_the_row(tmp_path, capsys):
    """Two frames 1e-6 s apart were tracked as such (the truth's physics and the filter step at least 1e-4 s, the
    floor `rate_hz` keeps at 10 kHz); now one line naming the CSV, the later image's line, both times and the
    floor, nothing written. Equal and decreasing times (refused before) name their lines too; frames 1e-4 s apart,
    also since an epoch (a step off 1e-4 by rounding), are read."""
    src = frames(tmp_path / "seq", NAMES)
    rows = ("img_0000.png,0\n", "img_0002.png,0.500001\n", "img_0001.png,0.5\n", "img_0003.png,1.5\n")
    times = csv_times(tmp_path, "file,t_s\n" + "".join(rows))  # rows out of name order: img_0002 on line 3
    code = main(["track", "--images", str(src), "--timestamps", times, "--out", str(tmp_path / "never"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert "times.csv: line 3: img_0002.png at t = 0.500001 s is 1e-06 s after img_0001.png at t = 0.5 s " \
           "(line 4): expected times that increase in the images' name order by at least 0.0001 s" in err[0], err
    assert not (tmp_path / "never").exists()
    for t2, said in (("0.5", "does not follow"), ("0.25", "does not follow"), ("0.50009", "is 9e-05 s after")):
        bad = csv_times(tmp_path, f"file,t_s\nimg_0000.png,0\nimg_0001.png,0.5\nimg_0002.png,{t2}\nimg_0003.png,1.5\n")
        with pytest.raises(InputError, match=rf"line 4: img_0002.png at t = {t2} s {said} img_0001.png at t = 0.5 s "
                                             r"\(line 3\): .*at least 0.0001 s"):
            read_timestamps(bad, NAMES)
    for t0 in (0.0, 1.7e9, 0.1):
        fast = csv_times(tmp_path, "file,t_s\n" + "".join(f"{n},{t0 + i * 1e-4!r}\n" for i, n in enumerate(NAMES)))
        assert len(read_timestamps(fast, NAMES)) == 4


def test_the_frame_names_floor_is_the_trackers():
    from envisat_pose.pipelines.runs import frame_names
    from envisat_pose.pipelines.tracking.tracker_bounds import MIN_FRAME_DT_S

    assert frame_names.MIN_FRAME_DT_S == MIN_FRAME_DT_S
