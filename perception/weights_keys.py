"""The keys of a weights file's metadata (perception/weights.py: safetensors' string-to-string metadata), each
named here once: the verb that fits a value writes it under its key, one reader reads it back (JSON strings;
perception/detect.py's and perception/keypoint_detect.py's readers). A leaf module: the network modules and the
weights' reader import it alike.

Each fit owns a set of keys (the *_KEYS tuples below): a refit rewrites its whole set (perception/weights.py's
with_metadata, drop=), so no key outlives the fit it came from (an error model measured on sequences beside sigmas
refitted on random views: measured for other sigmas). The sets overlap only in the error model; the refinement's
floor (the line fits' covariances, which replace the network's) and the face cue (the images under the labelled
pose, no detector) depend on no other fit's keys."""

FORMAT_KEY = "format"  # FORMAT or KEYPOINT_FORMAT
MODEL_CONFIG_KEY = "model_config"  # the architecture (ModelConfig or KeypointModelConfig)
KIND_KEY = "kind"  # a keypoint network's kind (perception/keypoint_net.MODEL_KIND; none: ENVISAT's corners)
TARGET_KEY = "target"  # a keypoint network's target: name, sha256, keypoint names (JSON)
COV_SCALE_KEY = "cov_scale"  # the corner network's covariance scale (`envisat calibrate`, `envisat adapt`)
COV_CALIBRATION_KEY = "cov_calibration"  # ... and the record of its fit
ERROR_MODEL_KEY = "error_model"  # perception/errormodel.ErrorModel (calibrate on sequences, adapt's scale)
ERROR_MODEL_RECORD_KEY = "error_model_record"  # ... and the record of its measurement
ADAPTATION_KEY = "adaptation"  # what `envisat adapt` adapted the weights on (JSON: the frames, the base weights)
REFINE_FLOOR_KEY = "refine_cov_floor_px2"  # the refinement's covariance floor, px^2 (`calibrate --refine`)
REFINE_CALIBRATION_KEY = "refine_cov_calibration"  # ... and the record of its fit
FACE_CUE_KEY = "face_cue"  # the half-turn's appearance cue (perception/facecue.FaceCue)
FACE_CUE_RECORD_KEY = "face_cue_record"  # ... and the record of its fit
SIGMA_KEY = "keypoint_sigma_px"  # a keypoint network's isotropic sigma per keypoint, px (`calibrate --target`)
SIGMA_RECORD_KEY = "keypoint_cov_calibration"  # ... and the record of its fit
REJECT_KEY = "keypoint_reject_curve"  # ... and what a correct track's gate rejects (perception/keypoint_cov.py)

ERROR_MODEL_KEYS = (ERROR_MODEL_KEY, ERROR_MODEL_RECORD_KEY)  # measured only on sequences, for the fit beside it
COV_CALIBRATION_KEYS = (COV_SCALE_KEY, COV_CALIBRATION_KEY, *ERROR_MODEL_KEYS)  # `envisat calibrate`
REFINE_CALIBRATION_KEYS = (REFINE_FLOOR_KEY, REFINE_CALIBRATION_KEY)  # `envisat calibrate --refine`
FACE_CUE_KEYS = (FACE_CUE_KEY, FACE_CUE_RECORD_KEY)  # `envisat calibrate --face-cue`
KEYPOINT_CALIBRATION_KEYS = (SIGMA_KEY, SIGMA_RECORD_KEY, REJECT_KEY, *ERROR_MODEL_KEYS)  # `calibrate --target`
