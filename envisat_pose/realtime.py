"""The real-time factor of a job over camera frames (`envisat run`, `envisat track`): the time the frames span
over the wall time that processed them."""

from __future__ import annotations


def real_time_factor(t_s, wall_s: float, period_s: float | None = None) -> float:
    """Time the frames t_s (s) span, one frame period included (period_s; default the median interval), over the
    wall time that processed them: above 1 the job keeps up with the camera. The one formula of `envisat run`
    and `envisat track`."""
    import numpy as np

    t = np.asarray(t_s, dtype=float)
    if period_s is None:
        period_s = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    span = float(t[-1] - t[0]) + period_s if len(t) else 0.0
    return span / max(float(wall_s), 1e-9)
