"""A user's video as pipelines/runs/frames.py reads it: its frames as stored.

A phone's recording holds its frames as the sensor gave them and tells players how to turn them for display (a
track's display matrix, the 'rotate' tag: 90 for a phone held upright). OpenCV's FFmpeg reader turns the frames by
it (CAP_PROP_ORIENTATION_AUTO, on by default: 80 x 48 px stored, read as 48 x 80). Pose needs the pixels as stored
(the camera's intrinsics describe the sensor's pixels), as for an image's EXIF Orientation (frame_pixels.py):
`open_video` turns that off, refuses a reader that cannot be told so, and `rotation_caution` tells the user once.
"""

from __future__ import annotations

import contextlib

from envisat_pose.config_errors import InputError

# how a player shows the stored frames, by the rotation OpenCV reports (CAP_PROP_ORIENTATION_META, degrees)
PLAYED = {90: "turned 90 deg clockwise", 180: "turned 180 deg", 270: "turned 90 deg counter-clockwise"}


def quiet_opencv() -> None:
    """OpenCV's own logger off (its warnings would otherwise reach the terminal)."""
    import cv2

    with contextlib.suppress(Exception):
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)


def stored_rotation(path: str, rotation_meta: float, auto_after: float, reader: str = "") -> int:
    """The rotation a video's frames carry (degrees, 0 for none or where the reader reports none: -1) given what its
    reader reports once told not to apply it (auto_after: CAP_PROP_ORIENTATION_AUTO, -1 for a reader without it,
    which turns nothing); InputError naming the video where the reader would still turn its frames."""
    rotation = int(round(rotation_meta)) % 360 if rotation_meta >= 0 else None
    if auto_after > 0 and rotation != 0:
        by = f"by its rotation metadata ({rotation} deg)" if rotation else "by a rotation it does not report"
        raise InputError(f"source {path!r}: OpenCV's video reader{f' ({reader})' if reader else ''} turns the frames "
                         f"{by} and cannot be told not to; expected frames as stored (the camera's intrinsics describe "
                         "them): a copy of the video without its rotation metadata")
    return rotation or 0


def open_video(path: str):
    """(cv2.VideoCapture of path whose frames come as stored, not turned by its rotation metadata; the cautions to warn
    of once: rotation_caution's); a capture that did not open is returned as it is (the caller says so)."""
    import cv2

    quiet_opencv()
    cap = cv2.VideoCapture(path)
    if not cap.isOpened():
        return cap, []
    meta = cap.get(cv2.CAP_PROP_ORIENTATION_META)
    cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 0)
    try:
        rotation = stored_rotation(path, meta, cap.get(cv2.CAP_PROP_ORIENTATION_AUTO), cap.getBackendName())
    except InputError:
        cap.release()
        raise
    size_px = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
    return cap, rotation_caution(path, rotation, size_px)


def rotation_caution(path: str, rotation: int, size_px: tuple[int, int]) -> list[str]:
    """What to warn of, once, for a video whose rotation metadata turns it for display (rotation, degrees; size_px:
    its frames as stored, width x height): they are used as stored, so the intrinsics must describe those; [] for
    none."""
    if not rotation:
        return []
    shown = PLAYED.get(rotation, f"turned {rotation} deg")
    return [f"source {path!r}: the video's rotation metadata says {rotation} deg (players show its frames {shown}): "
            f"they are used as stored ({size_px[0]} x {size_px[1]} px), not turned as a player shows them, so the "
            "camera's intrinsics (`camera`: fx, fy, cx, cy, width, height) must describe the stored frames"]
