"""Weights as safetensors (no pickle): the model's state plus its ModelConfig in the file's metadata.

Two kinds of detector weights: ENVISAT's corner network (format FORMAT, no target recorded: corners A-H) and another
target's keypoint network (perception/keypoint_net.py: format KEYPOINT_FORMAT, kind 'keypoints', the target's
name, sha256 and keypoint names), by default FILE_detector.safetensors beside the target file
(default_target_weights). check_weights_target refuses weights of another target than the one a verb is
given, in one line, before any work (envisat_pose/target.require_weights_target).

A missing, truncated or foreign file, or one whose tensors do not fit the model, is one WeightsError line
naming the file and the problem. Optimizer state (training only) is torch.save of tensors and plain containers,
read back with torch.load(weights_only=True), which refuses anything else.
"""

from __future__ import annotations

import json
import os
import pickle

import torch

from envisat_pose.config import InputError, from_dict
from envisat_pose.io import atomic_path
from envisat_pose.perception.keypoint_net import KEYPOINT_FORMAT
from envisat_pose.perception.model import CornerNet, ModelConfig
from envisat_pose.perception.weights_keys import FORMAT_KEY, MODEL_CONFIG_KEY, TARGET_KEY
from envisat_pose.target import DEFAULT_TARGET, require_weights_target, resolve_target_path

FORMAT = "envisat-pose corner detector v1"


class WeightsError(InputError):
    """A weights file that cannot be used: the message names the file and the problem."""


def shipped_weights_path() -> str:
    """The project's shipped detector weights (package data `envisat_pose.models/detector.safetensors`, with its
    model card detector.json beside it). WeightsError naming the path when the file is absent."""
    import importlib.resources

    path = str(importlib.resources.files("envisat_pose.models").joinpath("detector.safetensors"))
    if not os.path.isfile(path):
        raise WeightsError(f"{path}: the shipped detector weights are missing (give `weights`)")
    return path


TARGET_WEIGHTS_SUFFIX = "_detector.safetensors"  # another target's default weights: FILE_detector... beside FILE.xml


def default_target_weights(target: str) -> str:
    """The default weights of another target than ENVISAT (target: its MJCF file as given): its own keypoint
    detector, FILE_detector.safetensors beside the target file (the shipped upper stage's
    models/upper_stage_detector.safetensors; a user's, saved beside their MJCF file); its path as the user typed the
    target where that names the same file, else where it lies. Used only when its header names that target (its
    sha256): else an InputError naming `weights`, in one line, and where it was looked for, as the user typed the
    target (no path of this machine where they typed none). The header only, before any work."""
    name = os.path.splitext(os.path.basename(target))[0] + TARGET_WEIGHTS_SUFFIX
    typed = os.path.join(os.path.dirname(target), name)
    if not os.path.isfile(resolve_target_path(target)):  # the file first: no default of a file that is not there
        raise InputError(f"target {target!r}: expected an MJCF file (no such file)")
    beside = os.path.join(os.path.dirname(resolve_target_path(target)), name)
    if not os.path.isfile(beside):
        packaged = os.path.samefile(os.path.dirname(beside), os.path.dirname(shipped_weights_path()))
        raise InputError(f"weights '': none given, and target {target!r} has no keypoint detector of its own at "
                         f"{typed!r} (the shipped weights are ENVISAT's corner network): train it (`envisat train "
                         f"--target {target}`), calibrate it (`envisat calibrate --target {target}`) and give it "
                         f"(--weights){'' if packaged else f', or save it as {typed!r}'}")
    try:
        require_weights_target(typed, trained_for(beside, read_header(beside)), target,
                               "the default beside the target file is")
    except InputError as err:
        raise InputError(f"weights '': none given, and {str(err).replace(beside, typed)} (--weights)") from None
    return typed if os.path.isfile(typed) and os.path.samefile(typed, beside) else beside


def write_safetensors(path: str, tensors: dict, metadata: dict[str, str]) -> None:
    """tensors and metadata as a safetensors file at path, atomically and byte-reproducibly: safetensors writes its
    metadata map in a random order (a Rust HashMap's: the same weights gave other bytes, so other sha256 records),
    so the header is written again with the metadata's keys sorted (the tensors and their offsets unchanged; the
    header padded with spaces to 8 bytes, as safetensors pads it)."""
    from safetensors.torch import save

    data = save(tensors, metadata=metadata)
    n = int.from_bytes(data[:8], "little")
    header = json.loads(data[8:8 + n])
    if "__metadata__" in header:
        header["__metadata__"] = dict(sorted(header["__metadata__"].items()))
    text = json.dumps(header, separators=(",", ":"), ensure_ascii=False).encode()
    text += b" " * (-len(text) % 8)
    with atomic_path(path, suffix=".safetensors") as tmp:
        with open(tmp, "wb") as fh:
            fh.write(len(text).to_bytes(8, "little"))
            fh.write(text)
            fh.write(memoryview(data)[8 + n:])


def save_weights(path: str, model: CornerNet, extra: dict | None = None) -> None:
    """Write the model's state (parameters and buffers) and its config atomically as safetensors."""
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    meta = {FORMAT_KEY: FORMAT, MODEL_CONFIG_KEY: json.dumps(model.cfg.to_dict(), sort_keys=True)}
    if hasattr(model, "metadata"):  # another target's keypoint network: its format, kind and target
        meta.update(model.metadata())
    for k, v in (extra or {}).items():
        meta[k] = v if isinstance(v, str) else json.dumps(v, sort_keys=True)
    write_safetensors(path, state, meta)


def read_weights(path: str) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """(tensors, metadata) of a safetensors file; WeightsError when it is missing or not one."""
    from safetensors import SafetensorError
    from safetensors.torch import safe_open

    if not os.path.exists(path):
        raise WeightsError(f"{path}: no such weights file")
    if os.path.isdir(path):
        raise WeightsError(f"{path}: is a folder, expected a .safetensors weights file")
    try:
        with safe_open(path, framework="pt", device="cpu") as fh:
            meta = dict(fh.metadata() or {})
            tensors = {k: fh.get_tensor(k) for k in fh.keys()}
    except (SafetensorError, OSError, ValueError, RuntimeError) as err:
        first = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise WeightsError(f"{path}: not a readable safetensors file ({first})") from None
    return tensors, meta


def read_metadata(path: str) -> dict[str, str]:
    """The metadata of a weights file (strings; JSON values as text)."""
    return read_weights(path)[1]


def read_header(path: str) -> dict[str, str]:
    """The metadata of a weights file read from its header alone (no tensor loaded); WeightsError as read_weights."""
    from safetensors import SafetensorError
    from safetensors.torch import safe_open

    if not os.path.isfile(path):
        raise WeightsError(f"{path}: no such weights file")
    try:
        with safe_open(path, framework="pt", device="cpu") as fh:
            return dict(fh.metadata() or {})
    except (SafetensorError, OSError, ValueError, RuntimeError) as err:
        first = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise WeightsError(f"{path}: not a readable safetensors file ({first})") from None


def trained_for(path: str, meta: dict[str, str]) -> dict | None:
    """The target keypoint weights record ({'name', 'sha256', 'keypoint_names'}), or None for ENVISAT's corner
    weights (and any other format: its loader names it). WeightsError for a keypoint file without its record."""
    if meta.get(FORMAT_KEY) != KEYPOINT_FORMAT:
        return None
    try:
        record = json.loads(meta[TARGET_KEY])
        if not isinstance(record, dict) or not isinstance(record.get("sha256"), str):
            raise ValueError("no sha256")
    except (KeyError, ValueError) as err:
        raise WeightsError(f"{path}: keypoint-detector weights without their target's record ({err})") from None
    return record


def check_weights_target(path: str, given: str, field: str = "weights", named: str | None = None) -> None:
    """InputError (one line naming the weights, as `named` where given: the user's words for path; their target and
    `given`) unless the weights at path were trained for the target `given` (a `target` value; DEFAULT_TARGET:
    ENVISAT): the header only, before any work."""
    meta = read_header(path)
    require_weights_target(named or path, trained_for(path, meta), given, field)


def with_metadata(src: str, dst: str, extra: dict, drop: tuple[str, ...] = ()) -> dict[str, str]:
    """Copy a weights file to dst (atomically) with the keys in drop removed, then extra's entries added or replaced
    (e.g. cov_scale). drop: the keys a fit owns (perception/weights_keys.py's *_KEYS), so that a refit leaves none
    of the earlier fit's behind. Returns the entries removed (those of drop src had and extra does not write)."""
    tensors, meta = read_weights(src)
    removed = {k: meta.pop(k) for k in drop if k in meta and k not in extra}
    for k, v in extra.items():
        meta[k] = v if isinstance(v, str) else json.dumps(v, sort_keys=True)
    write_safetensors(dst, tensors, meta)
    return removed


def load_model(path: str, device: str = "cpu") -> CornerNet:
    """The CornerNet stored in a weights file, in eval mode. WeightsError (one line) for a truncated or foreign
    file, a missing config, or tensors whose names or shapes do not fit."""
    tensors, meta = read_weights(path)
    if trained_for(path, meta) is not None:  # another target's keypoint network: refused naming its target
        require_weights_target(path, trained_for(path, meta), DEFAULT_TARGET)
    if meta.get(FORMAT_KEY) != FORMAT or MODEL_CONFIG_KEY not in meta:
        raise WeightsError(f"{path}: not corner-detector weights (metadata {FORMAT_KEY} {meta.get(FORMAT_KEY)!r})")
    try:
        cfg = from_dict(ModelConfig, json.loads(meta[MODEL_CONFIG_KEY]))
    except (ValueError, TypeError) as err:
        raise WeightsError(f"{path}: bad model config in the metadata ({err})") from None
    model = CornerNet(cfg)
    load_state(model, tensors, path)
    return model.to(device).eval()


def load_state(model: torch.nn.Module, tensors: dict[str, torch.Tensor], path: str) -> None:
    """Copy tensors into the model after checking names, shapes and dtypes (WeightsError naming the first)."""
    want = model.state_dict()
    missing = sorted(set(want) - set(tensors))
    extra = sorted(set(tensors) - set(want))
    if missing or extra:
        what = f"missing {missing[0]!r}" if missing else f"unexpected {extra[0]!r}"
        raise WeightsError(f"{path}: tensors do not fit the model: {what} "
                           f"({len(missing)} missing, {len(extra)} unexpected)")
    for k, v in want.items():
        if tuple(tensors[k].shape) != tuple(v.shape):
            raise WeightsError(f"{path}: tensor {k!r} has shape {tuple(tensors[k].shape)}, the model's is "
                               f"{tuple(v.shape)}")
        if tensors[k].dtype != v.dtype:
            raise WeightsError(f"{path}: tensor {k!r} has dtype {tensors[k].dtype}, the model's is {v.dtype}")
        if v.is_floating_point() and not torch.isfinite(tensors[k]).all():
            raise WeightsError(f"{path}: tensor {k!r} holds non-finite values")
    model.load_state_dict(tensors, strict=True)


BACKBONE_PREFIXES = ("stem.", "hourglass.", "neck.")  # the layers CornerNet and KeypointNet share (model.py)


def load_backbone(model: torch.nn.Module, path: str) -> int:
    """Copy the backbone (stem, hourglass and neck) of any detector's weights at path (ENVISAT's corner network or
    a keypoint network) into model, its heads left as they are; the number of tensors copied. WeightsError naming
    the first backbone tensor the file lacks or holds in another shape (a backbone of another width or depth)."""
    tensors, _ = read_weights(path)
    want = {k: v for k, v in model.state_dict().items() if k.startswith(BACKBONE_PREFIXES)}
    for k, v in want.items():
        if k not in tensors:
            raise WeightsError(f"{path}: no backbone tensor {k!r} (not detector weights of this backbone)")
        if tuple(tensors[k].shape) != tuple(v.shape) or tensors[k].dtype != v.dtype:
            raise WeightsError(f"{path}: backbone tensor {k!r} is {tuple(tensors[k].shape)} {tensors[k].dtype}, "
                               f"the model's {tuple(v.shape)} {v.dtype} (another width, depth or stem)")
        if v.is_floating_point() and not torch.isfinite(tensors[k]).all():
            raise WeightsError(f"{path}: tensor {k!r} holds non-finite values")
    model.load_state_dict({**model.state_dict(), **{k: tensors[k] for k in want}}, strict=True)
    return len(want)


def save_tensors(path: str, state: dict) -> None:
    """torch.save of a state made of tensors and plain containers (optimizer state), atomically."""
    with atomic_path(path, suffix=".pt") as tmp:
        torch.save(state, tmp)


def load_tensors(path: str) -> dict:
    """Read back save_tensors with weights_only=True (no arbitrary unpickling); WeightsError if unreadable."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise WeightsError(f"{path}: no such file") from None
    except pickle.UnpicklingError:  # torch's text offers to load it unsafely: not ours to offer
        raise WeightsError(f"{path}: holds Python objects besides tensors; refused (such a file is never "
                           "unpickled here)") from None
    except Exception as err:  # torch raises many types for foreign or truncated files
        first = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise WeightsError(f"{path}: not a readable tensor state ({type(err).__name__}: {first})") from None
