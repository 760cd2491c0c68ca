"""A recording's entity paths name keypoints for every target (`/world/keypoints_true`, `.../keypoints_detected`,
`metrics/visible_keypoints`): they said corners (`/world/corners_true`) for a CubeSat's 12 keypoints too. The
blueprint each file carries names the paths its data holds: a view's contents that matched no entity would open
empty. `envisat view` opens a file with the blueprint written in it, so a recording written before the rename
(corners paths, and a blueprint naming them) still shows as it did."""

import os
import sys

import cv2
import numpy as np
import rerun as rr

from envisat_pose.analysis import recording
from envisat_pose.analysis.recording import read_recording
from envisat_pose.target import load_target

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the folder's own helpers
from test_recording_layout_doc import tracked_run  # noqa: E402

CUBESAT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "models", "cubesat_3u.xml")


def entities(path) -> set[str]:
    static, temporal = read_recording(str(path))
    return set(static) | set(temporal)


def blueprint_queries(path) -> list[tuple[str, str]]:
    """(view origin, include expression with $origin filled in) of every view's contents in the file's blueprint."""
    reader = rr.chunk.RrdReader(str(path))
    (store,) = reader.blueprints()
    origins, queries = {}, {}
    for chunk in reader.stream(store=store).collect().stream():
        batch = chunk.to_record_batch()
        cols = {n: batch.column(n).to_pylist()[-1] for n in batch.schema.names if ":" in n}
        if "ViewBlueprint:space_origin" in cols:
            origins[chunk.entity_path] = cols["ViewBlueprint:space_origin"][0]
        if "ViewContents:query" in cols:
            queries[chunk.entity_path.removesuffix("/ViewContents")] = cols["ViewContents:query"]
    return [(origins[v], q.replace("$origin", origins[v])) for v, qs in queries.items() for q in qs
            if not q.startswith("-")]


def matched(query: str, held: set[str]) -> bool:
    """Whether an include expression ('a/b', 'a/b/**') names an entity the file holds."""
    base = "/" + query.removesuffix("/**").strip("/")
    return any(e == base or (query.endswith("/**") and e.startswith(base + "/")) for e in held)


def samples(tmp_path, target=None):
    png = cv2.imencode(".png", np.full((48, 64), 90, np.uint8))[1].tobytes()
    depth = cv2.imencode(".png", np.full((48, 64), 25000, np.uint16))[1].tobytes()
    K = [[80.0, 0, 31.5], [0, 80.0, 23.5], [0, 0, 1]]
    n = 8 if target is None else target.num_keypoints
    px = np.random.default_rng(0).uniform(5, 40, (n, 2)).tolist()
    label = {"visible": [True] * n, "in_frame": [True] * n, "K": K, "R_cam_from_target": np.eye(3).tolist(),
             "t_cam_from_target_m": [0.0, 0.0, 50.0], "depth_scale_m": 0.002, "scene": {"t_s": 0.0}}
    label |= {"corners_px": px} if target is None else {"keypoints_px": px, "keypoint_names": target.keypoint_names}
    path = tmp_path / f"ds_{n}.rrd"
    sample = recording.Sample("k0", png, label, np.zeros((48, 64), np.uint8), depth)
    recording.write_samples_recording(str(path), [sample], target=target)
    return path


def test_every_recording_names_keypoints_and_its_blueprint_names_what_it_holds(tmp_path):
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate_truth

    cubesat = load_target(CUBESAT)
    files = {}
    for target in (None, cubesat):
        name = "envisat" if target is None else "cubesat"
        cfg = scenario_config("default", duration_s=4.0, **({} if target is None else {"target": {"file": CUBESAT}}))
        files[f"{name} truth"] = tmp_path / f"{name}_truth.rrd"
        recording.write_truth_recording(str(files[f"{name} truth"]), simulate_truth(cfg), target=target)
        files[f"{name} samples"] = samples(tmp_path, target)
    files["tracked run"] = tmp_path / "run.rrd"
    tracked_run(files["tracked run"], with_truth=True)

    for what, path in files.items():
        held = entities(path)
        assert not [e for e in held if "corners" in e], what
        unmatched = [q for _, q in blueprint_queries(path) if not matched(q, held)]
        assert unmatched == [], (what, unmatched)
    assert {"/world/keypoints_true", "/world/chaser/camera/image/keypoints_true", "/metrics/visible_keypoints",
            "/metrics/in_frame_keypoints"} <= entities(files["cubesat truth"])
    assert "/world/chaser/camera/image/keypoints_true" in entities(files["cubesat samples"])
    assert {"/world/chaser/camera/image/keypoints_detected", "/world/chaser/camera/image/keypoints_estimated",
            "/world/chaser/camera/image/keypoints_true"} <= entities(files["tracked run"])
