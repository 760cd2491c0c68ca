"""Fixtures of the app tests: the detector weights the closed-loop tests run with."""

import pytest


@pytest.fixture(scope="session")
def detector_weights() -> str:
    """The shipped detector weights (models/detector.safetensors, package data): the closed loop's default."""
    from envisat_pose.app.run import default_weights_path

    return default_weights_path()
