"""What a wheel ships beside the code: every file the package finds by name at run time must be package data, or
a user who installs with pip (not the repository's editable set-up) meets 'no such file' where the README's
commands work here."""

import fnmatch
import os
import tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def models_package_data() -> list[str]:
    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as fh:
        return tomllib.load(fh)["tool"]["setuptools"]["package-data"]["envisat_pose.models"]


def shipped(name: str, patterns: list[str]) -> bool:
    return any(fnmatch.fnmatch(name, p) for p in patterns)


def test_every_shipped_target_and_its_detector_are_package_data():
    patterns = models_package_data()
    names = sorted(os.listdir(os.path.join(ROOT, "models")))
    targets = [n for n in names if n.endswith(".xml")]
    assert "envisat.xml" in targets and len(targets) >= 3
    for xml in targets:
        assert shipped(xml, patterns), xml
        stem = xml[: -len(".xml")]
        # a target's own detector beside its file (ENVISAT's is detector.safetensors) and its model card
        weights = "detector" if stem == "envisat" else f"{stem}_detector"
        for name in (f"{weights}.safetensors", f"{weights}.json"):
            if os.path.exists(os.path.join(ROOT, "models", name)):
                assert shipped(name, patterns), f"models/{name} is not in the wheel's package data"


def test_the_leg_weights_stay_out_of_the_wheel():
    # the training legs' weights are the repository's record (docs/history.md), not what a user runs
    patterns = models_package_data()
    legs = [n for n in os.listdir(os.path.join(ROOT, "models")) if "_leg" in n]
    assert legs, "the test reads the repository's models folder"
    assert not [n for n in legs if shipped(n, patterns)]
