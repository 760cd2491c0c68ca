"""A phone's video whose rotation metadata (its track's display matrix, ffprobe's 'rotate') turns it for display
(pipelines/runs/frame_video.py): OpenCV's FFmpeg reader turned its frames by it (80 x 48 px stored, read as 48 x
80); now they are read as stored and the source is warned of once, naming the video and the rotation, as for an
image's EXIF Orientation. The videos are written here with cv2.VideoWriter and their matrix set by hand; a reader
that would still turn the frames (none in this OpenCV) is tested through the decision on its property values."""

import struct
import warnings

import numpy as np
import pytest

from envisat_pose.config_errors import InputError
from envisat_pose.pipelines.runs.frame_video import stored_rotation
from envisat_pose.pipelines.runs.frames import open_source, scan_source

H, W = 48, 80  # stored: wider than high, so a turn by 90 deg shows in the shape
# the track header's matrix (a, b, u, c, d, v, x, y, w; 16.16 and 2.30 fixed point) a player turns the frames by
MATRIX = {0: (1, 0, 0, 0, 1), 90: (0, 1, 0, -1, 0), 180: (-1, 0, 0, 0, -1), 270: (0, -1, 0, 1, 0)}


def rotated_video(path, rotation):
    """An MPEG-4 video of 5 gray frames whose left quarter is white, its track header's matrix turning it by
    `rotation` degrees for display (what a phone held upright writes: 90)."""
    import cv2

    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (W, H), False)
    if not writer.isOpened():
        pytest.skip("this OpenCV writes no MPEG-4 video")
    frame = np.zeros((H, W), np.uint8)
    frame[:, : W // 4] = 255
    for _ in range(5):
        writer.write(frame)
    writer.release()
    data = path.read_bytes()
    at = data.index(b"tkhd") + 4  # version, flags, two times, track id, reserved, duration, reserved, layer...
    wide = data[at] == 1
    matrix_at = at + 4 + (16 if wide else 8) + 8 + (8 if wide else 4) + 16
    a, b, u, c, d = MATRIX[rotation]
    matrix = struct.pack(">9i", a << 16, b << 16, u, c << 16, d << 16, 0, 0, 0, 1 << 30)
    path.write_bytes(data[:matrix_at] + matrix + data[matrix_at + 36:])


def rotation_warnings(source):
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        scan_source(source)
    return [str(w.message) for w in seen if "rotation" in str(w.message)]


@pytest.mark.parametrize("rotation, shown", [(90, "turned 90 deg clockwise"), (180, "turned 180 deg"),
                                             (270, "turned 90 deg counter-clockwise")])
def test_a_rotated_video_is_read_as_stored_and_warned_of_once(tmp_path, rotation, shown):
    path = tmp_path / f"phone_{rotation}.mp4"
    rotated_video(path, rotation)
    source = open_source(str(path), 0.0)
    said = rotation_warnings(source)
    assert source.size_px == (W, H)  # as stored, not as a player shows it
    assert len(said) == 1, said
    assert f"source {str(path)!r}: the video's rotation metadata says {rotation} deg" in said[0]
    assert f"players show its frames {shown}" in said[0] and f"used as stored ({W} x {H} px)" in said[0]
    for _, frame in source.frames():
        assert frame.shape == (H, W) and frame[:, : W // 4 - 2].min() > 200 and frame[:, W // 4 + 2:].max() < 60


def test_a_video_without_rotation_is_not_warned_of(tmp_path):
    path = tmp_path / "plain.mp4"
    rotated_video(path, 0)
    source = open_source(str(path), 0.0)
    assert rotation_warnings(source) == [] and source.size_px == (W, H)


def test_a_reader_that_would_still_turn_the_frames_is_refused():
    """stored_rotation(path, CAP_PROP_ORIENTATION_META, CAP_PROP_ORIENTATION_AUTO once set to 0): FFmpeg's reader
    reports the rotation and turns it off (0); a reader without the properties (-1) turns nothing."""
    assert stored_rotation("v.mp4", 90.0, 0.0) == 90 and stored_rotation("v.mp4", 270.0, 0.0) == 270
    assert stored_rotation("v.mp4", 0.0, 1.0) == 0 and stored_rotation("v.mp4", -1.0, -1.0) == 0
    assert stored_rotation("v.mp4", 90.0, -1.0) == 90
    with pytest.raises(InputError, match=r"source 'v\.mp4': OpenCV's video reader \(X\) turns the frames by its "
                                         r"rotation metadata \(90 deg\) and cannot be told not to"):
        stored_rotation("v.mp4", 90.0, 1.0, "X")
    with pytest.raises(InputError, match="by a rotation it does not report"):
        stored_rotation("v.mp4", -1.0, 1.0)
