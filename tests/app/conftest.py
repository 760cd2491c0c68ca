"""Fixtures of the app tests: the detector weights the closed-loop tests run with."""

import pytest


@pytest.fixture(scope="session")
def detector_weights() -> str:
    """The shipped detector weights (models/detector.safetensors, package data): the closed loop's default."""
    from envisat_pose.pipelines.common.job_defaults import default_weights_path

    return default_weights_path()


def _verify_rrd(path) -> None:
    """`rerun rrd verify` (the installed rerun-sdk's CLI) passes on the file: it loads, and its footer is there."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "RERUN_ANALYTICS": "0"}
    p = subprocess.run([sys.executable, "-m", "rerun_cli", "rrd", "verify", str(path)], capture_output=True,
                       text=True, env=env, timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr


@pytest.fixture(scope="session")
def verify_rrd():
    """A check that a recording passes `rerun rrd verify`."""
    return _verify_rrd
