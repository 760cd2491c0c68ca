"""envisat-pose: relative pose of the tumbling ENVISAT from camera images (docs/design.md).

The public API, imported on first use (so `import envisat_pose` loads nothing heavy):

- contracts: `TruthTrajectory`, `Detections`, `Estimates` (envisat_pose.contracts);
- the tracker: `Tracker` (`Tracker.from_scenario`), `TrackerConfig`, `TrackEstimate`, `tracker_from_scenario`
  (envisat_pose.pipelines.tracking.tracker); what it is built from: `tracker_camera`, `tracker_detector`, `chaser_from_orbit`,
  `tracker_filter` (envisat_pose.pipelines.tracking.build);
- the closed loop: `RunConfig`, `run_closed_loop` (envisat_pose.pipelines.runs.closed_loop); a user's frames:
  `TrackConfig`, `open_source`, `track_frames` (envisat_pose.pipelines.runs.track);
- a truth and its estimate: `ScenarioConfig` (envisat_pose.datagen.scenario), `run_simulate`
  (envisat_pose.pipelines.campaigns.simulate), `EstimateConfig`, `run_estimate` (envisat_pose.pipelines.campaigns.estimate);
- campaigns: `MonteCarloConfig`, `run_campaign` (envisat_pose.pipelines.campaigns.campaign), `RunnerConfig`
  (envisat_pose.pools: the local pool or Dask), `write_report` (envisat_pose.pipelines.campaigns.report);
- datasets: `GenerateConfig` (envisat_pose.datagen.generate_config), `run_generate` (envisat_pose.datagen.factory),
  `verify_dataset`, `dataset_stats` (envisat_pose.datagen.dataset), `inspect_dataset`
  (envisat_pose.pipelines.datasets.inspect), `ExportConfig`, `export_dataset` (envisat_pose.pipelines.datasets.export);
- the detector: `TrainConfig` (envisat_pose.perception.train), `train_detector` (envisat_pose.pipelines.detector.train),
  `DetectJobConfig`, `run_detect` (envisat_pose.pipelines.detector.detect), `run_evaluate`
  (envisat_pose.pipelines.detector.evaluate), `CalibrateJobConfig`, `run_calibration`
  (envisat_pose.pipelines.detector.calibrate), `AdaptConfig`, `adapt` (envisat_pose.pipelines.adaptation.adapt);
  another target's keypoint detector (`--target`): `TargetDetectJobConfig`, `run_detect_target`,
  `evaluate_target_detector`, `run_calibrate_target` (envisat_pose.pipelines.detector.*_target);
- the target: `Target`, `load_target` (envisat_pose.target: one spacecraft from its MJCF file; ENVISAT's by default);
- the state's layout: `envisat_pose.state`.
"""

_PUBLIC = {
    "TruthTrajectory": "envisat_pose.contracts", "Detections": "envisat_pose.contracts",
    "Estimates": "envisat_pose.contracts",
    "Tracker": "envisat_pose.pipelines.tracking.tracker", "TrackerConfig": "envisat_pose.pipelines.tracking.tracker",
    "TrackEstimate": "envisat_pose.pipelines.tracking.tracker",
    "tracker_camera": "envisat_pose.pipelines.tracking.build", "tracker_detector": "envisat_pose.pipelines.tracking.build",
    "chaser_from_orbit": "envisat_pose.pipelines.tracking.build", "tracker_filter": "envisat_pose.pipelines.tracking.build",
    "tracker_from_scenario": "envisat_pose.pipelines.tracking.tracker",
    "RunConfig": "envisat_pose.pipelines.runs.closed_loop", "run_closed_loop": "envisat_pose.pipelines.runs.closed_loop",
    "TrackConfig": "envisat_pose.pipelines.runs.track", "open_source": "envisat_pose.pipelines.runs.track",
    "track_frames": "envisat_pose.pipelines.runs.track",
    "MonteCarloConfig": "envisat_pose.pipelines.campaigns.campaign", "run_campaign": "envisat_pose.pipelines.campaigns.campaign",
    "TrainConfig": "envisat_pose.perception.train", "train_detector": "envisat_pose.pipelines.detector.train",
    "ScenarioConfig": "envisat_pose.datagen.scenario", "run_simulate": "envisat_pose.pipelines.campaigns.simulate",
    "EstimateConfig": "envisat_pose.pipelines.campaigns.estimate",
    "run_estimate": "envisat_pose.pipelines.campaigns.estimate", "RunnerConfig": "envisat_pose.pools",
    "write_report": "envisat_pose.pipelines.campaigns.report",
    "GenerateConfig": "envisat_pose.datagen.generate_config", "run_generate": "envisat_pose.datagen.factory",
    "verify_dataset": "envisat_pose.datagen.dataset", "dataset_stats": "envisat_pose.datagen.dataset",
    "inspect_dataset": "envisat_pose.pipelines.datasets.inspect",
    "ExportConfig": "envisat_pose.pipelines.datasets.export", "export_dataset": "envisat_pose.pipelines.datasets.export",
    "DetectJobConfig": "envisat_pose.pipelines.detector.detect", "run_detect": "envisat_pose.pipelines.detector.detect",
    "run_evaluate": "envisat_pose.pipelines.detector.evaluate",
    "CalibrateJobConfig": "envisat_pose.pipelines.detector.calibrate",
    "run_calibration": "envisat_pose.pipelines.detector.calibrate",
    "TargetDetectJobConfig": "envisat_pose.pipelines.detector.detect_target",
    "run_detect_target": "envisat_pose.pipelines.detector.detect_target",
    "evaluate_target_detector": "envisat_pose.pipelines.detector.evaluate_target",
    "run_calibrate_target": "envisat_pose.pipelines.detector.calibrate_target",
    "AdaptConfig": "envisat_pose.pipelines.adaptation.adapt", "adapt": "envisat_pose.pipelines.adaptation.adapt",
    "Target": "envisat_pose.target", "load_target": "envisat_pose.target",
}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    if name in _PUBLIC:
        import importlib

        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'envisat_pose' has no attribute {name!r}")
