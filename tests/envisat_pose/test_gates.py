"""The chi-square bounds (envisat_pose/gates.py) against scipy.stats.chi2, the independent reference, and the
verbs' start without scipy.stats (the bounds use its kernels in scipy.special: 0.7 s less at every start)."""

import os
import subprocess
import sys

import numpy as np
import pytest
from scipy.stats import chi2

from envisat_pose.gates import chi2_bound, chi2_gate, chi2_quantile

DOFS = np.array([1.0, 2.0, 3.0, 6.0, 7.5, 12.0, 16.0, 96.0, 1200.0])
PROBS = np.array([1e-9, 1e-5, 0.00135, 0.025, 0.5, 0.975, 0.99, 0.99865, 0.99999])


def test_the_quantile_is_scipys_ppf():
    np.testing.assert_allclose(chi2_quantile(PROBS[:, None], DOFS), chi2.ppf(PROBS[:, None], DOFS), rtol=1e-12)
    assert chi2_quantile(0.99, 3) == pytest.approx(11.3449, abs=1e-4)  # a printed table's value
    assert isinstance(chi2_quantile(0.5, 2), float)


def test_the_bound_and_the_gate_are_scipys_isf():
    np.testing.assert_allclose(chi2_bound(PROBS[:, None], DOFS), chi2.isf(PROBS[:, None], DOFS), rtol=1e-12)
    assert chi2_gate(0.99999, 2) == pytest.approx(23.0259, abs=1e-4)  # -2 ln(1e-5), the 2-dof closed form
    with pytest.raises(ValueError, match="probability"):
        chi2_gate(1.0, 2)


def test_the_command_line_starts_without_scipy_stats():
    code = "import sys, envisat_pose.app.cli; print('scipy.stats' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         cwd=os.path.dirname(os.path.abspath(__file__)))
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"
