"""Lay the checkout out as the installed package, without a build step (for a machine with no network and no
compiler setup, e.g. a borrowed GPU machine): every package pyproject.toml names, copied from its folder (the
stage folders at the root land inside envisat_pose, as the wheel installs them), the compiled gravity plugin
copied in from a carried folder, and a dist-info whose entry_points.txt holds the console script and the
`mujoco.plugins` entry, so that `import mujoco` loads the plugin. Standard library only.

    python3 scripts/gpu_layout.py DEST [--plugin-from DIR]     then PYTHONPATH=DEST
"""

from __future__ import annotations

import argparse
import glob
import os
import shutil
import sys
import tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PLUGIN_GLOB = "_relative_gravity*.so"


def package_folders(pyproject: dict) -> dict[str, str]:
    """{package name: its folder relative to the root} from [tool.setuptools] packages and package-dir."""
    tool = pyproject["tool"]["setuptools"]
    mapping = tool.get("package-dir", {})
    out = {}
    for name in tool["packages"]:
        if name in mapping:
            out[name] = mapping[name]
        else:  # the nearest mapped parent, else the name as a path
            parts = name.split(".")
            for i in range(len(parts) - 1, 0, -1):
                parent = ".".join(parts[:i])
                if parent in mapping:
                    out[name] = os.path.join(mapping[parent], *parts[i:])
                    break
            else:
                out[name] = os.path.join(*parts)
    return out


def entry_points_text(project: dict) -> str:
    """entry_points.txt of the project's [project.scripts] and [project.entry-points.*]."""
    groups = {"console_scripts": project.get("scripts", {}), **project.get("entry-points", {})}
    return "".join(f"[{g}]\n" + "".join(f"{k} = {v}\n" for k, v in sorted(eps.items())) + "\n"
                   for g, eps in groups.items() if eps)


def copy_package(src: str, dst: str) -> int:
    """The package folder's own files (not its sub-packages' folders, which are packages of their own, nor
    caches or compiled plugins). Returns the number of files copied."""
    os.makedirs(dst, exist_ok=True)
    n = 0
    for name in sorted(os.listdir(src)):
        path = os.path.join(src, name)
        if os.path.isfile(path) and not name.endswith((".pyc", ".so")):
            shutil.copy2(path, os.path.join(dst, name))
            n += 1
    return n


def lay_out(dest: str, plugin_from: str | None = None, root: str = ROOT) -> dict:
    """Write the package under dest (replacing what is there). plugin_from: a folder holding the compiled plugin
    (default: the checkout's own datagen/plugin). Returns {"packages": n, "files": n, "plugin": file name}."""
    with open(os.path.join(root, "pyproject.toml"), "rb") as fh:
        pyproject = tomllib.load(fh)
    project = pyproject["project"]
    if os.path.isdir(dest):
        shutil.rmtree(dest)
    folders = package_folders(pyproject)
    files = 0
    for name, folder in folders.items():
        files += copy_package(os.path.join(root, folder), os.path.join(dest, *name.split(".")))
    plugin_pkg = next(n for n in folders if n.endswith(".plugin"))
    source = plugin_from or os.path.join(root, folders[plugin_pkg])
    found = sorted(glob.glob(os.path.join(source, PLUGIN_GLOB)))
    if not found:
        raise SystemExit(f"gpu_layout: no compiled plugin ({PLUGIN_GLOB}) in {source}: build it here "
                         "(pip install -e .) and carry it")
    shutil.copy2(found[0], os.path.join(dest, *plugin_pkg.split(".")))
    dist = os.path.join(dest, f"{project['name'].replace('-', '_')}-{project['version']}.dist-info")
    os.makedirs(dist)
    with open(os.path.join(dist, "METADATA"), "w", encoding="utf-8") as fh:
        fh.write(f"Metadata-Version: 2.1\nName: {project['name']}\nVersion: {project['version']}\n")
    with open(os.path.join(dist, "entry_points.txt"), "w", encoding="utf-8") as fh:
        fh.write(entry_points_text(project))
    return {"packages": len(folders), "files": files, "plugin": os.path.basename(found[0])}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)  # stdlib only
    ap.add_argument("dest", help="folder to lay the package out in (replaced); then PYTHONPATH=dest")
    ap.add_argument("--plugin-from", metavar="DIR", help="folder holding the compiled plugin (default: the checkout's)")
    args = ap.parse_args()
    r = lay_out(args.dest, args.plugin_from)
    print(f"laid out {r['packages']} packages ({r['files']} files) and {r['plugin']} in {args.dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
