"""One home for the tracker's statuses: envisat_pose/status.py. A tuple, list or dict of two or more status names
anywhere else in the package (every layer's folder: the core, the stages, pipelines/, app/), the benches or the
scripts is a second definition (as the four copies issue 29 found were). The folders are read from the build's
package-dir, so a layer added or moved is scanned without editing this file (the scan once stopped short of
pipelines/ and app/ when they moved). The checker runs on source text, so a test shows it catching a planted copy."""

import ast
import os
import tomllib

from envisat_pose.status import STATUSES

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
HOME = os.path.join("envisat_pose", "status.py")
EXTRA = ("bench", "scripts")  # not installed, but they read statuses too


def scanned_folders(root: str = ROOT) -> tuple[str, ...]:
    """The core, every folder pyproject.toml maps into envisat_pose, and the extra folders."""
    with open(os.path.join(root, "pyproject.toml"), "rb") as fh:
        package_dir = tomllib.load(fh)["tool"]["setuptools"]["package-dir"]
    return ("envisat_pose", *sorted(package_dir.values()), *EXTRA)


FOLDERS = scanned_folders()


def status_tables(source: str) -> list[int]:
    """Line numbers of literals (tuple, list, set, dict keys) naming two or more statuses."""
    out = []
    for node in ast.walk(ast.parse(source)):
        items = node.keys if isinstance(node, ast.Dict) else getattr(node, "elts", None)
        if not isinstance(node, (ast.Tuple, ast.List, ast.Set, ast.Dict)) or items is None:
            continue
        names = {n.value for n in items if isinstance(n, ast.Constant) and n.value in STATUSES}
        if len(names) >= 2:
            out.append(node.lineno)
    return out


def test_status_names_are_defined_once():
    found = {}
    for folder in FOLDERS:
        for dirpath, dirnames, filenames in os.walk(os.path.join(ROOT, folder)):
            dirnames[:] = [d for d in dirnames if d != "__pycache__"]
            for name in filenames:
                path = os.path.join(dirpath, name)
                rel = os.path.relpath(path, ROOT)
                if name.endswith(".py") and rel != HOME:
                    lines = status_tables(open(path, encoding="utf-8").read())
                    if lines:
                        found[rel] = lines
    assert not found, f"status names defined outside {HOME}: {found}"


def test_every_layer_folder_is_scanned():
    for layer in ("envisat_pose", "datagen", "perception", "filtering", "analysis", "pipelines", "app", "bench",
                  "scripts"):
        assert layer in FOLDERS, layer
    assert all(os.path.isdir(os.path.join(ROOT, f)) for f in FOLDERS), FOLDERS


def test_the_checker_catches_a_planted_copy():
    assert status_tables('NAMES = ("acquiring", "tracking", "lost")\n') == [1]
    assert status_tables('LEGEND = {"tracking": 1, "coasting": 3}\n') == [1]
    assert status_tables('s = est.status == "tracking"\n') == []
