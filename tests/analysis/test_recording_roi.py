"""The tracker recording's region of interest (analysis/recording_stream.py): the window (x0, y0, side) px the
detector looked at is drawn over the image as the box covering exactly its pixels, in the image's coordinates
as the recording draws points (pixel i spans [i, i + 1], so a keypoint at u is drawn at u + 0.5); a frame
without a window clears it."""

import numpy as np

from envisat_pose.analysis import recording
from envisat_pose.analysis.recording import read_recording
from envisat_pose.geometry import load_camera

ROI = "/world/chaser/camera/image/roi"


def estimate(roi_px) -> dict:
    K = 8
    return {"t_s": 0.0, "x_hat": np.r_[0.0, 50.0, 0.0, np.zeros(9)], "P": np.eye(12) * 0.01, "status": 1,
            "p_best": 1.0, "nis": 3.0, "nis_dof": 10, "corners_px": np.full((K, 2), np.nan),
            "visible": np.zeros(K, bool), "rejected": np.zeros(K, bool), "roi_px": np.asarray(roi_px, float)}


def test_the_region_of_interest_box_covers_the_windows_pixels_and_is_cleared_without_one(tmp_path):
    path = tmp_path / "track.rrd"
    rec = recording.TrackRecorder(f"save:{path}", load_camera(), with_truth=False)
    x0, y0, side = 300, 120, 64  # the window's pixels: columns 300..363, rows 120..183
    rec.log_frame(0, estimate([x0, y0, side]), None)
    rec.log_frame(1, estimate([np.nan] * 3), None)
    rec.close()
    _, temporal = read_recording(path)
    rows = temporal[ROI]
    k0, k1 = rows["frame"].index(0), rows["frame"].index(1)
    center = np.array(rows["Boxes2D:centers"][k0][0], float)
    half = np.array(rows["Boxes2D:half_sizes"][k0][0], float)
    # pixel u's square is [u, u + 1]: the window's first pixel starts at x0, its last ends at x0 + side
    np.testing.assert_allclose(center - half, [x0, y0], atol=1e-6)
    np.testing.assert_allclose(center + half, [x0 + side, y0 + side], atol=1e-6)
    assert not rows.get("Boxes2D:centers", [None] * (k1 + 1))[k1]  # frame 1: the box cleared, not held over
