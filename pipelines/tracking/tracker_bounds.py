"""The bounds of the tracker's config (tracker_config.py) and of the frame rates its jobs take, each with the reason
a value beyond it gives no meaningful job (a traceback, a warning per frame, a fit that never moves, a threshold
that bounds nothing physical). Values that mean "off" by design stay accepted where their docstrings say so
(bank.frame_max_log 0, integrity.recall_s 0, array_cue.per_frame 0)."""

from __future__ import annotations

import math
import sys

from envisat_pose.datagen.scenario import EARTH_RADIUS_M, MAX_TURN_PER_PHYSICS_STEP_RAD, MIN_PHYSICS_DT_S
from envisat_pose.filtering.dynamics import MU_EARTH_M3_S2
from envisat_pose.filtering.filter_config import SIGMA_MAX, SIGMA_MIN

# The longest gap a started track is predicted over, s (11.6 days): the propagation's steps, time and memory grow
# with it (a frame 1e300 s on was a numpy error from the filter, 1e8 s minutes of work for one frame), for a
# prior long since lost (a day's gap left a track's position sigma at hundreds of m: lost by its integrity tests).
# The cold start's fit propagates across its window's gaps and a lost track's memory to its recall the same way.
MAX_PREDICTION_S = 1e6
# The least interval between frames, s: the least step of the truth's physics and of the filter's RK4
# (datagen.scenario.MIN_PHYSICS_DT_S, filtering.filter_config.MIN_RK4_STEP_S); a camera faster than 10 kHz is
# faster than either resolves, and a cold-start gap below it restarts the window at every frame.
MIN_FRAME_DT_S = MIN_PHYSICS_DT_S
# A covariance's factor (acquire.start_cov_factor, integrity.recall_cov_factor): at most the ratio of the widest
# variance the filter takes to the least, (SIGMA_MAX / SIGMA_MIN)^2 = 1e48 (filter_config.MAX_OUTAGE_Q_SCALE's
# reason): a larger one takes even the least variance past the widest (1e300 made a started bank's covariance inf).
MAX_COV_FACTOR = (SIGMA_MAX / SIGMA_MIN) ** 2
# fit.huber, whitened residuals (sigmas): the IRLS weights min(1, huber / |r|) scale the fit's normal equations; at
# 1e-300 they fell below its 1e-12 damping and the fit never left its guess (rate 4.9e-3 rad/s off, 3e-5 fitted:
# default truth, frames 100-139 at 0.5 px); 1e-6 still fits. At 1e6 every corner already counts fully (least
# squares: the way to turn the down-weighting off); at 1e300 each weight's division overflowed (a warning per fit).
MIN_HUBER, MAX_HUBER = 1e-6, 1e6
# The most nats a log-likelihood bound may be (bank.appearance_max_log, bank.frame_max_log, array_cue.per_frame,
# array_cue.max_log): log of the largest double, 709.8; the likelihood ratio of a larger one is no double (its exp
# overflows), and the bank's probabilities are exps of these sums.
MAX_LOG_NATS = math.log(sys.float_info.max)
# The fastest tumble the truth's RK4 follows at its least physics step (0.05 rad per 1e-4 s step: 500 rad/s,
# 28648 deg/s); a tumble-rate bound beyond it bounds no state a run can hold.
MAX_RATE_DEG_S = math.degrees(MAX_TURN_PER_PHYSICS_STEP_RAD / MIN_PHYSICS_DT_S)
# Two bodies in Earth orbit (or leaving it) meet at most at twice the escape speed at the Earth's surface,
# 2 sqrt(2 mu / R_E) = 22.4 km/s; a relative-speed bound beyond it bounds no state a run can hold.
MAX_SPEED_M_S = 2.0 * math.sqrt(2.0 * MU_EARTH_M3_S2 / EARTH_RADIUS_M)
# integrity.min_target_px: the box spans at least a pixel (under one its corners are not told apart: the range bound
# lies beyond where any corner is seen) and at most the largest image side the jobs take (4096 px: a box required
# to span more than a frame has its range bound inside itself at every resolution the jobs take)
MIN_TARGET_PX, MAX_TARGET_PX = 1.0, 4096.0
# The most frames a run takes (RunConfig's duration_s x rate_hz), and integrity.window's most: a longer window never
# fills, and its arrays are allocated whole (2^63 - 1 frames: a numpy error at the first start)
MAX_RUN_FRAMES = 200_000
