"""What a tracker's recording (TrackRecorder: `envisat run`, `track`, `demo`) shows at each frame, read back with
Rerun's own chunk reader and resolved as the viewer's latest-at query does: the newest row at or before the frame,
a Clear (of the entity, or a recursive one of a parent) hiding what came before it, static data never cleared and
shadowing the temporal. An entity with no pose is drawn at its parent's origin: world's, the chaser's.

- No truth (a user's frames): no true target is drawn (its solid surface stood at the chaser, on the camera).
- The estimate (pose, skeleton, 3-sigma ellipsoid) is shown at the frames that have one, tracking or coasting,
  and at no other: not at the chaser before the first estimate, not at the last estimate while lost.
- A frame without an image (the Earth's shadow) shows none, not the last lit frame's."""

from collections import defaultdict

import numpy as np
import rerun as rr

from envisat_pose.analysis.recording import TrackRecorder
from envisat_pose.geometry import load_camera
from envisat_pose.target import load_target

UPPER_STAGE = "models/upper_stage.xml"
ACQUIRING, TRACKING, LOST, COASTING = 0, 1, 2, 3


def read_rows(path):
    """{entity: [(frame or None for static, row id, {column: value})]} in the file's row order (Rerun's reader)."""
    out = defaultdict(list)
    for chunk in rr.chunk.RrdReader(str(path)).stream():
        d = chunk.to_record_batch().to_pydict()
        ids = d.pop("rerun.controls.RowId")
        frames = d.pop("frame", [None] * len(ids))
        d.pop("sim_time", None)
        for i, (f, rid) in enumerate(zip(frames, ids)):
            out[chunk.entity_path].append((f, rid, {k: v[i] for k, v in d.items() if v[i] is not None}))
    return out


def latest(rows, entity, column, frame):
    """The value of `column` at `entity` the viewer shows at `frame` (None: nothing)."""
    for f, _, cols in rows.get(entity, []):
        if f is None and column in cols:
            return cols[column]  # static: shadows every time, never cleared
    events = []  # (frame, row id, value or None for a clear)
    parents = ["/".join(entity.split("/")[:i]) or "/" for i in range(2, entity.count("/") + 1)]
    for e in [entity, *parents]:
        for f, rid, cols in rows.get(e, []):
            if f is None or f > frame:
                continue
            if "Clear:is_recursive" in cols and (e == entity or cols["Clear:is_recursive"]):
                events.append((f, rid, None))
            elif e == entity and column in cols:
                events.append((f, rid, cols[column]))
    return max(events, key=lambda ev: (ev[0], ev[1]))[2] if events else None


def estimate(target, status, x, image_px=64):
    K = target.num_keypoints
    return {"t_s": 0.0, "x_hat": x, "P": np.eye(12) * 1e-3, "status": status, "p_best": 0.9, "nis": 2.0,
            "nis_dof": 4, "corners_px": np.full((K, 2), np.nan), "visible": np.zeros(K, bool),
            "rejected": np.zeros(K, bool), "roi_px": np.full(3, np.nan)}


def record(path, with_truth, statuses, images):
    """A recording of the upper stage over frames with the given statuses and images (None: no frame)."""
    target = load_target(UPPER_STAGE)
    cam = load_camera().scaled(64, 64)
    rec = TrackRecorder(f"save:{path}", cam, with_truth=with_truth, target=target)
    x = np.zeros(12)
    x[:3] = cam.pos_C_m + cam.R_K_from_C.T @ np.array([0.0, 0.0, 60.0])
    for k, (status, image) in enumerate(zip(statuses, images)):
        est = estimate(target, status, x + 0.01 * k) | {"t_s": float(k)}
        rec.log_frame(k, est, image, x_true=x if with_truth else None)
    rec.close()
    return target, x


def test_a_run_without_truth_shows_the_estimate_only_where_there_is_one(tmp_path):
    path = tmp_path / "track.rrd"
    statuses = [ACQUIRING, ACQUIRING, TRACKING, COASTING, LOST, ACQUIRING, TRACKING]
    target, x = record(path, False, statuses, [np.full((64, 64), 40, np.uint8)] * len(statuses))
    rows = read_rows(path)
    # no truth: nothing under world/target (its surface would stand at the chaser, around the camera)
    assert not [e for e in rows if e == "/world/target" or e.startswith("/world/target/")], list(rows)
    for k, status in enumerate(statuses):
        shown = status in (TRACKING, COASTING)
        skeleton = latest(rows, "/world/target_est/model", "LineStrips3D:strips", k)
        keypoints = latest(rows, "/world/target_est/model/keypoints", "Points3D:positions", k)
        pose = latest(rows, "/world/target_est", "Transform3D:translation", k)
        ellipsoid = latest(rows, "/world/target_est/position_3sigma", "Ellipsoids3D:half_sizes", k)
        assert (skeleton is not None) == shown, (k, status, "skeleton")
        assert (keypoints is not None) == shown, (k, status, "keypoints")
        assert (pose is not None) == shown, (k, status, "pose")
        assert (ellipsoid is not None) == shown, (k, status, "ellipsoid")
        if shown:
            assert len(skeleton) == len(target.skeleton)  # the upper stage's own skeleton and 12 keypoints
            np.testing.assert_allclose(keypoints, target.keypoints_T_m, rtol=1e-6, atol=1e-5)
            np.testing.assert_allclose(pose[0], x[:3] + 0.01 * k, rtol=1e-6)  # this frame's estimate


def test_a_frame_without_an_image_shows_none_and_the_truth_draws_its_own_target(tmp_path):
    path = tmp_path / "run.rrd"
    frame = np.full((64, 64), 40, np.uint8)
    target, _ = record(path, True, [TRACKING] * 4, [frame, frame, None, frame])
    rows = read_rows(path)
    assert [latest(rows, "/world/chaser/camera/image", "EncodedImage:blob", k) is not None for k in range(4)] == \
        [True, True, False, True]
    # with a truth, world/target carries the true pose and the target's own surface (the upper stage's mesh)
    assert latest(rows, "/world/target", "Transform3D:translation", 0) is not None
    positions = np.array(latest(rows, "/world/target/model", "Mesh3D:vertex_positions", 0))
    assert len(positions) == 3 * len(target.mesh().faces)
    np.testing.assert_allclose(positions.min(axis=0), target.mesh().vertices_T_m.min(axis=0), atol=1e-4)


def test_the_true_keypoints_in_the_image_are_named_as_the_detected_ones(tmp_path):
    """A tracker's .../image/keypoints_true carry their keypoint ids in the target's annotation class (named on hover,
    as the detections and a simulate recording's true keypoints are), only those seen (in_frame), at +0.5 px."""
    target = load_target(UPPER_STAGE)
    K = target.num_keypoints
    rec = TrackRecorder(f"save:{tmp_path / 'run.rrd'}", load_camera().scaled(64, 64), with_truth=True, target=target)
    px = np.arange(2 * K, dtype=float).reshape(K, 2)
    seen = np.arange(K) % 3 != 1
    x = np.zeros(12)
    x[1] = 50.0
    rec.log_frame(0, estimate(target, ACQUIRING, x), None, x_true=x, corners_true_px=px, in_frame=seen)
    rec.close()
    rows = read_rows(tmp_path / "run.rrd")
    entity = "/world/chaser/camera/image/keypoints_true"
    assert latest(rows, entity, "Points2D:keypoint_ids", 0) == np.flatnonzero(seen).tolist()
    assert latest(rows, entity, "Points2D:class_ids", 0) == [0]  # recording_layout.KEYPOINT_CLASS
    np.testing.assert_allclose(latest(rows, entity, "Points2D:positions", 0), px[seen] + 0.5)
