"""Chi-square bounds derived from their probability and degrees of freedom (the one home of the concept).

A gate is never a number typed by hand: a squared Mahalanobis distance of `dof` degrees of freedom, when the
noise model holds, stays under `chi2_gate(prob, dof)` with probability `prob` (a corner of 2 pixel components
at prob 0.99999: 23.03). `chi2_bound(tail_prob, dof)` is the same bound from the other side: exceeded with
probability `tail_prob` (the NIS window's false-alarm bound). tests/test_architecture.py refuses a gate typed
as a literal anywhere else.
"""

from __future__ import annotations

import numpy as np

# scipy.stats.chi2's own kernels: importing scipy.stats would cost 0.7 s at every verb's start
from scipy.special import chdtri, gammaincinv

# the per-corner gate probability of the filter and the tracker (FilterConfig.gate_prob's default)
GATE_PROB = 0.99999


def chi2_bound(tail_prob: float, dof) -> float | np.ndarray:
    """The chi-square value exceeded with probability tail_prob at dof degrees of freedom: chi2.isf. dof a
    number or an array (broadcast)."""
    out = chdtri(dof, tail_prob)  # the same bits as scipy.stats.chi2.isf(tail_prob, dof)
    return float(out) if np.ndim(out) == 0 else out


def chi2_quantile(prob, dof) -> float | np.ndarray:
    """The chi-square value under which a draw of dof degrees of freedom falls with probability prob: chi2.ppf
    (its same bits). prob and dof numbers or arrays (broadcast)."""
    out = 2.0 * gammaincinv(np.asarray(dof, float) / 2.0, prob)
    return float(out) if np.ndim(out) == 0 else out


def chi2_gate(prob: float, dof) -> float | np.ndarray:
    """The gate a chi-square distance of dof degrees of freedom passes with probability prob (0 < prob < 1):
    chi2.isf(1 - prob, dof) (the same bits as chi2.ppf(prob, dof))."""
    if not 0.0 < prob < 1.0:
        raise ValueError(f"gate probability {prob!r}: expected a probability in (0, 1)")
    return chi2_bound(1.0 - prob, dof)
