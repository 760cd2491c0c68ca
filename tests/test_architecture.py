"""The layers of design.md, checked by parsing every import of the package's source.

core (envisat_pose/*.py) imports no stage and no app; a stage (datagen, perception, filtering, analysis)
imports only the core, never another stage nor the app; only the app layer (envisat_pose/app/) combines
stages. Imports inside functions count too, and so do relative imports and the old top-level names.
"""

import ast
import os

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STAGES = ("datagen", "perception", "filtering", "analysis")
# where each layer's files live in the repository, and their import name
LAYOUT = {"envisat_pose": "envisat_pose", **{s: f"envisat_pose.{s}" for s in STAGES}}


def source_files():
    """(path, module name) of every .py file of the package, the stage folders mapped into envisat_pose."""
    for folder, package in LAYOUT.items():
        for dirpath, dirnames, filenames in os.walk(os.path.join(ROOT, folder)):
            dirnames[:] = [d for d in dirnames if d != "__pycache__"]
            if folder == "envisat_pose" and os.path.relpath(dirpath, ROOT) != "envisat_pose":
                if not os.path.relpath(dirpath, ROOT).startswith(os.path.join("envisat_pose", "app")):
                    continue
            for name in filenames:
                if name.endswith(".py"):
                    path = os.path.join(dirpath, name)
                    rel = os.path.relpath(path, os.path.join(ROOT, folder))[:-3].replace(os.sep, ".")
                    mod = package if rel == "__init__" else f"{package}.{rel.removesuffix('.__init__')}"
                    yield path, mod


def imported_modules(path: str, module: str) -> list[tuple[int, str]]:
    """Every module an import statement in the file names, relative imports resolved."""
    tree = ast.parse(open(path, encoding="utf-8").read(), path)
    is_pkg = path.endswith("__init__.py")
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base[: len(base) - node.level + (1 if is_pkg else 0)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            out.append((node.lineno, name))
            out += [(node.lineno, f"{name}.{a.name}") for a in node.names]  # `from pkg import stage`
    return out


def layer_of(module: str) -> str | None:
    """'app', a stage name, 'core', a forbidden bare stage name ('bare:...'), or None (not ours)."""
    parts = module.split(".")
    if parts[0] in STAGES:
        return f"bare:{parts[0]}"
    if parts[0] != "envisat_pose":
        return None
    if len(parts) > 1 and parts[1] == "app":
        return "app"
    if len(parts) > 1 and parts[1] in STAGES:
        return parts[1]
    return "core"


def violations() -> list[str]:
    found = []
    for path, module in source_files():
        own = layer_of(module)
        for line, name in imported_modules(path, module):
            other = layer_of(name)
            if other is None or other == own:
                continue
            where = f"{os.path.relpath(path, ROOT)}:{line} imports {name}"
            if other.startswith("bare:"):
                found.append(f"{where}: the stages install inside envisat_pose")
            elif own == "core" and other != "core":
                found.append(f"{where}: the core imports no stage and no app")
            elif own in STAGES and other != "core":
                found.append(f"{where}: a stage imports only the core")
    return found


def test_layers_follow_the_import_rule():
    assert violations() == []


def test_the_checker_sees_a_crossing(tmp_path):
    """The rule test can fail: a stage importing another stage (inside a function) is reported."""
    bad = tmp_path / "filtering"
    bad.mkdir()
    (bad / "x.py").write_text("def f():\n    from envisat_pose.datagen.truth import simulate\n    from ..analysis import plots\n")
    found = []
    for line, name in imported_modules(str(bad / "x.py"), "envisat_pose.filtering.x"):
        if layer_of(name) not in (None, "core", "filtering"):
            found.append(name)
    assert "envisat_pose.datagen.truth" in found and "envisat_pose.analysis" in found


def test_every_stage_file_is_seen():
    mods = {m for _, m in source_files()}
    for stage in STAGES:
        assert f"envisat_pose.{stage}" in mods
    assert "envisat_pose.app.cli" in mods and "envisat_pose.contracts" in mods
