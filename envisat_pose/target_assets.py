"""The files a target file names (includes, attached models, meshes, textures, height fields) and its sha256.

MuJoCo reads a file's assets relative to its folder and compiler (meshdir, texturedir), an attached model's relative
to that model's own file: absolute_asset_files makes them absolute so a spec compiles from anywhere. A target is
identified by its file's bytes and those of every file it names (target_sha256), cached per file and modification
time (named_files).
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
import xml.etree.ElementTree as ET

ASSET_FOLDERS = (("meshes", "meshdir"), ("hfields", "meshdir"), ("skins", "meshdir"), ("textures", "texturedir"))


def _absolute(name: str, folder: str, sub: str) -> str:
    return name if not name or os.path.isabs(name) else os.path.normpath(os.path.join(folder, sub or "", name))


def absolute_asset_files(spec, path: str) -> None:
    """Make the files of a spec's meshes, height fields, skins and textures (a cube's six faces too) absolute
    (relative to the folder of the file at `path` and its compiler's meshdir/texturedir; an asset of a model the
    file attaches (<attach model=...>) relative to that model's file and its compiler: attached_assets), so the
    spec compiles from anywhere."""
    folder = os.path.dirname(path)
    attached = attached_assets(path)
    for kind, sub in ASSET_FOLDERS:
        for asset in getattr(spec, kind):
            if (kind, asset.name) in attached:
                asset.file, cubefiles = attached[(kind, asset.name)]
                if any(cubefiles):
                    asset.cubefiles = list(cubefiles)
                continue
            asset.file = _absolute(asset.file, folder, getattr(spec, sub))
            if kind == "textures" and any(asset.cubefiles):
                asset.cubefiles = [_absolute(f, folder, spec.texturedir) for f in asset.cubefiles]


def attached_models(path: str) -> list[tuple[str, str]]:
    """(absolute file, prefix) of each model the MJCF file at `path` attaches (<attach model=... prefix=...>, its
    <model name=... file=...> relative to the file's folder; either may be in a file it includes), in file order;
    unreadable files skipped (MuJoCo's reading reports them)."""
    folder = os.path.dirname(path)
    models, attaches = {}, []
    for name in [path, *_included_files(path, folder)]:
        try:
            root = ET.parse(name).getroot()
        except (OSError, ET.ParseError):
            continue
        models.update({el.get("name"): os.path.normpath(os.path.join(folder, el.get("file", "")))
                       for el in root.iter("model") if el.get("file")})
        attaches += [(el.get("model"), el.get("prefix", "")) for el in root.iter("attach")]
    return [(models[m], prefix) for m, prefix in attaches if m in models and os.path.isfile(models[m])]


def attached_assets(path: str) -> dict[tuple[str, str], tuple[str, tuple[str, ...]]]:
    """{(kind, name in the attaching spec): (absolute file, absolute cube files)} of the assets of the models the
    file at `path` attaches (attached_models), theirs too: MuJoCo reads an attached model's asset files relative to
    that model's own file and compiler (meshdir, texturedir), which its spec keeps from no one (to_xml writes the
    bare names). Names carry the attach's prefix, as MuJoCo gives them."""
    import mujoco

    out: dict[tuple[str, str], tuple[str, tuple[str, ...]]] = {}
    for file, prefix in attached_models(path):
        try:
            child = mujoco.MjSpec.from_file(file)
        except ValueError:
            continue  # MuJoCo's reading of the attaching file reports it
        absolute_asset_files(child, file)
        for kind, _ in ASSET_FOLDERS:
            for asset in getattr(child, kind):
                out[(kind, prefix + asset.name)] = (asset.file, tuple(getattr(asset, "cubefiles", ())))
    return out


def asset_files(spec) -> set[str]:
    """Every file a spec's assets name (after absolute_asset_files: absolute), a cube texture's faces included."""
    named = {a.file for kind, _ in ASSET_FOLDERS for a in getattr(spec, kind)}
    named |= {f for t in spec.textures for f in t.cubefiles}
    return {f for f in named if f}

def _included_files(path: str, base: str) -> list[str]:
    """The files the MJCF file at `path` includes (<include file=...>, relative to the main file's folder base),
    and theirs, depth first; unreadable ones skipped (MuJoCo's reading reports them)."""
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError):
        return []
    out = []
    for el in root.iter("include"):
        name = os.path.normpath(os.path.join(base, el.get("file", "")))
        if os.path.isfile(name):
            out += [name, *_included_files(name, base)]
    return out


def named_files(path: str) -> tuple[str, ...]:
    """The files the target file at `path` names (includes, attached models, meshes, textures, height fields),
    absolute, sorted; none where no 'file...=' is in it (the shipped targets). Cached per file and modification
    time."""
    return _named_files(path, os.stat(path).st_mtime_ns)


@functools.lru_cache(maxsize=16)
def _named_files(path: str, mtime_ns: int) -> tuple[str, ...]:
    with open(path, "rb") as fh:
        if not re.search(rb"file[a-z]*\s*=", fh.read()):  # file=, or a cube texture's fileright= ...
            return ()
    import mujoco

    folder = os.path.dirname(path)
    named = set(_included_files(path, folder))
    for model, _ in attached_models(path):  # an attached model's file and those it names (its includes, models)
        named |= {model, *named_files(model)}
    try:
        spec = mujoco.MjSpec.from_file(path)
        absolute_asset_files(spec, path)
        named |= asset_files(spec)
    except ValueError:
        pass  # MuJoCo's reading reports it
    return tuple(sorted(named))


def target_sha256(path: str) -> str:
    """What identifies a target: the sha256 of its file's bytes and of each file it names (named_files: an edited
    mesh is another target), named relative to the file's folder. A file that names none hashes as its bytes."""
    with open(path, "rb") as fh:
        digest = hashlib.sha256(fh.read())
    for name in named_files(path):
        try:
            with open(name, "rb") as fh:
                body = fh.read()
        except OSError:
            continue  # MuJoCo's reading reports it
        digest.update(b"\0" + os.path.relpath(name, os.path.dirname(path)).encode() + b"\0" + body)
    return digest.hexdigest()
