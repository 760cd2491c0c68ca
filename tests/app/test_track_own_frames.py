"""A user's own frames brought to `envisat track` (a stress round): a video or an output folder whose name is not
UTF-8, multi-page TIFFs and animations, a dangling link among the frames, a manifest.json of another tool beside
the images, a timestamps CSV written on Windows, frames too far apart for the cold start, times since an epoch.
Small synthetic frames: what is checked is the input handling, not the tracking."""

import os
import subprocess
import sys

import numpy as np
import pytest

from envisat_pose.config import InputError
from envisat_pose.pipelines.runs.frames import open_source, scan_source

SIDE = 64


def frames(folder, names, seed=0):
    """Gray noise frames, one per name; returns the images written."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    imgs = [rng.integers(0, 256, (SIDE, SIDE), dtype=np.uint8) for _ in names]
    for n, img in zip(names, imgs):
        assert cv2.imwrite(str(folder / n), img)
    return imgs


def bytes_name(folder, raw: bytes) -> str:
    """A path in folder whose last name is the raw bytes (a Latin-1 name, as an old archive leaves it), as Python
    gives it (surrogates); skipped where the file system takes UTF-8 names only."""
    path = os.path.join(os.fsencode(str(folder)), raw)
    try:
        open(path, "wb").close()
        os.remove(path)
    except OSError:
        pytest.skip("this file system takes UTF-8 names only")
    return os.fsdecode(path)


def test_a_video_whose_name_is_not_utf8_is_refused_in_one_line(tmp_path):
    """clip_\\xe9.avi (Latin-1): OpenCV's video reader crashed the process (a segfault, exit 139, no message). Run
    in a child process, so that the crash is this test's failure, not the test session's end."""
    import cv2

    video = bytes_name(tmp_path, b"clip_\xe9.avi")
    w = cv2.VideoWriter(os.path.join(str(tmp_path), "clip.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 1.0,
                        (SIDE, SIDE), isColor=True)
    for img in frames(tmp_path / "f", ["a.png", "b.png"]):
        w.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    w.release()
    os.rename(os.path.join(str(tmp_path), "clip.avi"), os.fsencode(video))
    code = ("import os, sys\nfrom envisat_pose.config import InputError\n"
            "from envisat_pose.pipelines.runs.frames import open_source\n"
            "try:\n    open_source(os.fsdecode(bytes.fromhex(sys.argv[1])), 1.0)\n"
            "except InputError as err:\n    print(err)\n")
    p = subprocess.run([sys.executable, "-c", code, os.fsencode(video).hex()], capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, (p.returncode, p.stderr[-2000:])
    assert "clip_\\udce9.avi" in p.stdout and "not UTF-8" in p.stdout and "rename it" in p.stdout, p.stdout


def side_camera(tmp_path):
    """The MJCF camera read out at SIDE px: the camera of the noise frames."""
    from envisat_pose.geometry import load_camera

    cam = load_camera().scaled(SIDE, SIDE)
    path = tmp_path / "side_camera.toml"
    path.write_text(f"fx = {cam.f_px!r}\nfy = {cam.f_px!r}\ncx = {cam.cu_px!r}\ncy = {cam.cv_px!r}\n"
                    f"width = {SIDE}\nheight = {SIDE}\n")
    return str(path)


def test_an_output_folder_whose_name_is_not_utf8_is_refused_before_any_work(tmp_path, capsys):
    """--out run_\\xe9: every frame was read and tracked, then Rerun's writer raised a UnicodeEncodeError traceback.
    Now one line naming --out, before anything is read or made."""
    from envisat_pose.app.cli import main

    src = tmp_path / "seq"
    frames(src, [f"img_{i:04d}.png" for i in range(4)])
    cfg = tmp_path / "fast.toml"
    cfg.write_text("[tracker.acquire]\nframes = 3\n")
    out = bytes_name(tmp_path, b"run_\xe9")
    code = main(["track", "--images", str(src), "--rate-hz", "1", "--camera", side_camera(tmp_path), "--config",
                 str(cfg), "--out", out, "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert err.startswith("envisat track: error: --out ") and "not UTF-8" in err and "rename it" in err, err
    assert not os.path.exists(os.fsencode(out))
    from envisat_pose.analysis.sink_check import check_sink

    with pytest.raises(InputError, match=r"^sink .*not UTF-8"):  # a library caller's sink, and `envisat run`'s
        check_sink(f"save:{out}/recording.rrd")


def test_a_tiff_stack_is_refused_not_read_as_its_first_page(tmp_path):
    """A folder of TIFF stacks (a lab camera's output, 5 frames a file) was tracked as one frame a file, the rest
    of each stack lost without a word; the stack given alone was told to give its folder, which did the same."""
    import cv2

    src = tmp_path / "stacks"
    src.mkdir()
    imgs = frames(tmp_path / "pngs", [f"f{i}.png" for i in range(10)])
    for s in range(2):
        assert cv2.imwritemulti(str(src / f"stack_{s}.tif"), imgs[5 * s:5 * s + 5])
    source = open_source(str(src), 1.0)
    with pytest.raises(InputError, match=r"stack_0.tif: 5 frames in one file \(a multi-page TIFF or an animation\)"):
        scan_source(source)
    with pytest.raises(InputError, match=r"stack_0.tif': 5 frames in one image file.*one frame per file"):
        open_source(str(src / "stack_0.tif"), 1.0)
    source = open_source(str(tmp_path / "pngs"), 1.0)  # one frame a file: as before
    scan_source(source)
    assert len(source.t_s) == 10


def test_a_link_to_a_frame_that_is_gone_is_refused_not_skipped(tmp_path):
    """A folder of links into an archive, one of whose frames was purged: the dangling link was skipped, and with
    a timestamps CSV (its row for that frame ignored) the sequence lost the frame without a word."""
    names = [f"img_{i:04d}.png" for i in range(4)]
    store = tmp_path / "store"
    frames(store, names)
    src = tmp_path / "links"
    src.mkdir()
    for n in names:
        os.symlink(store / n, src / n)
    times = tmp_path / "times.csv"
    times.write_text("file,t_s\n" + "".join(f"{n},{i * 0.5}\n" for i, n in enumerate(names)))
    source = open_source(str(src), timestamps=str(times))  # links to frames: read as the frames
    scan_source(source)
    assert source.names == names
    os.remove(store / names[2])
    with pytest.raises(InputError, match=r"'img_0002.png' is a link to '.*store/img_0002.png', which does not "
                                         r"exist; expected an image file"):
        open_source(str(src), timestamps=str(times))


def test_another_tools_manifest_beside_the_images_leaves_an_image_folder(tmp_path):
    """A labelling tool's manifest.json beside the PNGs made the folder a generate folder: '--rate-hz does not
    apply to a generate folder', or without it 'manifest.json holds a JSON list'."""
    src = tmp_path / "seq"
    frames(src, [f"img_{i:04d}.png" for i in range(3)])
    for text in ('{"images": ["img_0000.png"], "camera": "nav"}', "[1, 2]", "not json"):
        (src / "manifest.json").write_text(text)
        source = open_source(str(src), 1.0)
        assert source.kind == "images" and source.names == [f"img_{i:04d}.png" for i in range(3)]
    os.remove(src / "img_0000.png")  # no images beside it: a generate folder's manifest, refused as one
    for n in ("img_0001.png", "img_0002.png"):
        os.remove(src / n)
    with pytest.raises(InputError, match=r"unreadable manifest.json"):
        open_source(str(src))


def test_times_since_an_epoch_are_read_and_ms_in_the_s_column_refused(tmp_path):
    """Times since 1970 in s are frame times as any (the tracker and the recording take them); the same times in
    ms in the t_s column were tracked, then the recording's clock (int64 ns) overflowed: a traceback after the
    work. Now one line naming the file and the time, before any frame is read."""
    from envisat_pose.pipelines.runs.frame_names import read_timestamps

    names = [f"img_{i:04d}.png" for i in range(3)]
    times = tmp_path / "times.csv"
    times.write_text("file,t_s\n" + "".join(f"{n},{1.7e9 + i}\n" for i, n in enumerate(names)))
    np.testing.assert_allclose(read_timestamps(str(times), names), 1.7e9 + np.arange(3))
    times.write_text("file,t_s\n" + "".join(f"{n},{1.7e12 + 1000 * i}\n" for i, n in enumerate(names)))
    with pytest.raises(InputError, match=r"times.csv: img_0000.png at t = 1.7e\+12 s: expected a time in s of at "
                                         r"most 9.22e\+09 s .*ms or us since an epoch"):
        read_timestamps(str(times), names)


def test_a_timestamps_csv_written_on_windows_is_read(tmp_path):
    """A CSV from a Windows tool: CRLF line ends and full Windows paths in the file column. 'no time for image
    img_0000.png' was said of a file whose row was there (its name read as the whole path)."""
    from envisat_pose.pipelines.runs.frame_names import read_timestamps

    names = [f"img_{i:04d}.png" for i in range(3)]
    times = tmp_path / "times.csv"
    times.write_bytes(("file,t_s\r\n" + "".join(f"C:\\Users\\me\\frames\\{n},{i * 0.5}\r\n"
                                                 for i, n in enumerate(names))).encode())
    np.testing.assert_allclose(read_timestamps(str(times), names), [0.0, 0.5, 1.0])


def test_frames_too_far_apart_for_the_cold_start_are_warned_of(tmp_path, capsys):
    """Times in ms in the t_s column (frames 1000 s apart): every frame restarted the cold start's window
    (max_gap_s 30 s), and the run said 'nothing tracked' without a reason. Now a warning says why, once the
    frames pass; frames 1 s apart say nothing."""
    from envisat_pose.app.cli import main
    from envisat_pose.pipelines.runs.frame_names import spacing_caution

    assert spacing_caution("s", np.arange(5) * 1000.0, 3, 30.0).startswith("source 's': no 3 frames in a row")
    assert spacing_caution("s", np.r_[0.0, 1000.0, 1001.0, 1002.0, 5000.0], 3, 30.0) is None  # three close
    names = [f"img_{i:04d}.png" for i in range(4)]
    src = tmp_path / "seq"
    frames(src, names)
    cfg = tmp_path / "fast.toml"
    cfg.write_text("[tracker.acquire]\nframes = 3\n")
    for step, warned in ((1000, True), (1, False)):
        times = tmp_path / "times.csv"
        times.write_text("file,t_s\n" + "".join(f"{n},{i * step}\n" for i, n in enumerate(names)))
        code = main(["track", "--images", str(src), "--timestamps", str(times), "--camera", side_camera(tmp_path),
                     "--config", str(cfg), "--out", str(tmp_path / "out"), "--quiet"])
        err = capsys.readouterr().err.strip()
        assert code == 0
        assert ("warning: --images" in err and "no 3 frames in a row are within 30 s" in err
                and "a median 1e+03 s apart" in err and "times in ms?" in err) == warned, err


def test_the_first_tracking_time_is_printed_whole_for_times_since_an_epoch():
    """'first tracking at t = 1.7e+09 s' said nothing of when, for frames timed since 1970."""
    from envisat_pose.pipelines.runs.outputs import status_line

    line = status_line(40, {"acquiring": 20, "tracking": 20}, 1700000033.5, "tracking", 0.2)
    assert "first tracking at t = 1700000033.5 s;" in line, line
    for t, said in ((20.0, "20"), (11 + 1 / 3, "11.333")):
        assert f"first tracking at t = {said} s;" in status_line(40, {"tracking": 20}, t, "tracking", 0.2)


def test_a_folder_that_cannot_be_listed_is_one_line(tmp_path, monkeypatch):
    """A folder of another user's without read permission (os.listdir's PermissionError, simulated: the tests may
    run as root, who reads any folder) was a traceback."""
    src = tmp_path / "theirs"
    frames(src, ["img_0000.png"])
    listdir = os.listdir

    def refused(path="."):
        if os.fspath(path) == str(src):
            raise PermissionError(13, "Permission denied", os.fspath(path))
        return listdir(path)

    monkeypatch.setattr(os, "listdir", refused)
    with pytest.raises(InputError, match=r"source '.*theirs': the folder cannot be listed \(Permission denied\)"):
        open_source(str(src), 1.0)


def test_signed_16_bit_frames_are_told_what_is_wrong_with_them(tmp_path):
    """A signed 16-bit TIFF (int16) was refused as 'pixels of type int16: expected 8- or 16-bit': it is 16-bit."""
    import cv2

    src = tmp_path / "signed"
    src.mkdir()
    for i in range(2):
        assert cv2.imwrite(str(src / f"f{i}.tif"), np.full((SIDE, SIDE), 1000 * i, np.int16))
    with pytest.raises(InputError, match=r"f0.tif: pixels of type int16: expected unsigned 8- or 16-bit integers"):
        scan_source(open_source(str(src), 1.0))
