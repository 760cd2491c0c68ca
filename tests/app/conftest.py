"""Fixtures of the app tests: the detector weights the closed-loop tests run with."""

import pytest


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: a test of a minute or more (runs by default, CI included; "
                            "deselect locally with -m 'not slow')")


@pytest.fixture(scope="session")
def detector_weights() -> str:
    """The shipped detector weights (models/detector.safetensors, package data): the closed loop's default."""
    from envisat_pose.app.run import default_weights_path

    return default_weights_path()
