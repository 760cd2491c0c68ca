"""envisat-pose: relative pose of the tumbling ENVISAT from camera images (docs/design.md).

The public API, imported on first use (so `import envisat_pose` loads nothing heavy):

- contracts: `TruthTrajectory`, `Detections`, `Estimates` (envisat_pose.contracts);
- the tracker: `Tracker` (`Tracker.from_scenario`), `TrackerConfig`, `TrackEstimate`, `tracker_from_scenario`
  (envisat_pose.pipelines.tracker); what it is built from: `tracker_camera`, `tracker_detector`, `chaser_from_orbit`,
  `tracker_filter` (envisat_pose.pipelines.build);
- the closed loop: `RunConfig`, `run_closed_loop` (envisat_pose.pipelines.closed_loop); a user's frames:
  `TrackConfig`, `open_source`, `track_frames` (envisat_pose.pipelines.track);
- campaigns: `MonteCarloConfig`, `run_campaign` (envisat_pose.pipelines.campaign);
- the detector: `TrainConfig` (envisat_pose.perception.train), `train_detector` (envisat_pose.pipelines.train);
- the state's layout: `envisat_pose.state`.
"""

_PUBLIC = {
    "TruthTrajectory": "envisat_pose.contracts", "Detections": "envisat_pose.contracts",
    "Estimates": "envisat_pose.contracts",
    "Tracker": "envisat_pose.pipelines.tracker", "TrackerConfig": "envisat_pose.pipelines.tracker",
    "TrackEstimate": "envisat_pose.pipelines.tracker",
    "tracker_camera": "envisat_pose.pipelines.build", "tracker_detector": "envisat_pose.pipelines.build",
    "chaser_from_orbit": "envisat_pose.pipelines.build", "tracker_filter": "envisat_pose.pipelines.build",
    "tracker_from_scenario": "envisat_pose.pipelines.tracker",
    "RunConfig": "envisat_pose.pipelines.closed_loop", "run_closed_loop": "envisat_pose.pipelines.closed_loop",
    "TrackConfig": "envisat_pose.pipelines.track", "open_source": "envisat_pose.pipelines.track",
    "track_frames": "envisat_pose.pipelines.track",
    "MonteCarloConfig": "envisat_pose.pipelines.campaign", "run_campaign": "envisat_pose.pipelines.campaign",
    "TrainConfig": "envisat_pose.perception.train", "train_detector": "envisat_pose.pipelines.train",
}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    if name in _PUBLIC:
        import importlib

        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'envisat_pose' has no attribute {name!r}")
