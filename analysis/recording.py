"""The Rerun logger: truth, estimates, error series and labelled samples written as a `.rrd` recording.

The one module of the project that talks to Rerun (design.md, Conventions). It takes plain arrays and the core's
contracts and writes the design's layout:

    world                                    the chaser's LVLH frame C, centred on the chaser (m); annotation
                                             context (the target's keypoint names and skeleton,
                                             envisat_pose.target.Target)
    world/target                             true pose of T in C (translation rho_C, rotation R_C_from_T)
    world/target/model                       the target's drawn surface, one Mesh3D in its materials' colours
                                             (static, in T)
    world/target_est                         run 0's estimated pose; .../model the target's skeleton (line
                                             segments) and .../model/keypoints its keypoints, .../position_3sigma
                                             the 3-sigma ellipsoid of the position covariance (axes in C, drawn in
                                             T_est); a tracker's run: only at frames with an estimate, and
                                             world/target only with a truth
    world/keypoints_true                     the truth's keypoint sites in C (ENVISAT: corners A-H; green visible,
                                             red hidden)
    world/chaser/camera                      the pinhole of models/envisat.xml (camera `chaser_cam`), static
    world/chaser/camera/image                the camera image (compressed PNG/JPEG) where there is one
    world/chaser/camera/image/keypoints_true the keypoints in the image (in frame; green visible, red hidden)
    world/chaser/camera/image/{mask,depth}   a dataset sample's segmentation and depth
    metrics/error/<block>/<axis>             error of every run (one series per run), with .../filter_3sigma (+-3
                                             sigma of the filter's P) and .../sample_3sigma (+-3 sigma of the runs'
                                             spread)
    metrics/nees/{value,band}                estimate, montecarlo: the NEES (12 dof) averaged over the runs, with
                                             the two-sided 95 % band of that mean (montecarlo: the campaign's, all
                                             runs)
    metrics/{range_m,visible_keypoints,in_frame_keypoints}
    __properties                             every recording's name (RecordingInfo), as the viewer lists it: its
                                             file's name and what it holds ("est.rrd: cubesat_3u estimates, 3
                                             runs"; a tracker's run: its title)

A tracker's run (TrackRecorder: `envisat run`, `track`, `demo`) logs frame by frame, beside world/target,
world/target_est and world/chaser/camera/image{,/keypoints_true} above (the true keypoints seen, with a truth):

    world/chaser/camera/image/keypoints_detected   the detector's keypoints (yellow; red: rejected by the gate)
    world/chaser/camera/image/keypoints_estimated  the target's keypoints projected from the estimate (blue)
    world/chaser/camera/image/roi                  the region of interest the detector read (a box; cleared
                                                   without)
    metrics/error/<block>/<axis>{,/filter_3sigma}  with a truth: the estimate's error and its +-3 sigma (from P)
    metrics/nees/{value,band}                      with a truth: the run's NEES (12 dof) and its 95 % band
    metrics/sigma3/{position_m,attitude_deg}/<axis>, metrics/range_est_m   without a truth: 3 sigma, range
    metrics/nis                                    the tracker's NIS / dof
    metrics/tracker/{status,p_best}                status code (status_legend) and best hypothesis' probability
    events                                         a line at every change of status (lost: the tracker's why)
    description, status_legend                     the run's title; the status codes' names (JSON)

Timelines: `sim_time` (duration, s) and `frame` (sequence: the truth's sample, the filter's step or the dataset's
sample index). Long series go in through `send_columns`; model data is logged once as static. Each file is
written under a temporary name, with its footer (`rerun rrd verify` passes), and renamed when complete
(envisat_pose.io.atomic_path).

Every writer takes the target (`target`, None: ENVISAT) and draws its own shape and keypoints.

One job a file: recording_layout.py (constants, the target's model, series loggers, blueprints), recording_writers.py
(recordings written whole from arrays), recording_reader.py (read back), recording_stream.py (TrackRecorder: a run
logged frame by frame). This module is their public face: the names in __all__ (what the app, the pipelines and
users import); every other name is imported from its own module.

Two conventions change at this edge: Rerun quaternions are (x, y, z, w), ours (w, x, y, z); Rerun's pixel (0, 0)
covers [0, 1]^2 (centre 0.5), ours follow OpenCV (centre 0), so image points and the principal point get +0.5.
"""

from __future__ import annotations

# the public face of the recording modules (see above): these names are re-exported on purpose
from .recording_reader import read_recording
from .recording_stream import TrackRecorder
from .recording_writers import (
    Sample,
    write_campaign_recording,
    write_estimates_recording,
    write_samples_recording,
    write_truth_recording,
)

__all__ = [
    "Sample",
    "TrackRecorder",
    "read_recording",
    "write_campaign_recording",
    "write_estimates_recording",
    "write_samples_recording",
    "write_truth_recording",
]
