"""Weights load without unpickling; a missing, truncated, foreign or wrong-shape file is one clear line."""

import os

import numpy as np
import pytest
import torch

from envisat_pose.perception.model import CornerNet, ModelConfig
from envisat_pose.perception.weights import WeightsError, load_model, load_tensors, save_tensors, save_weights


@pytest.fixture
def weights(tmp_path):
    model = CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8))
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.01)
    path = tmp_path / "w.safetensors"
    save_weights(str(path), model)
    return model, path


def _one_line(err):
    assert "\n" not in str(err.value)
    return str(err.value)


def test_round_trip(weights):
    model, path = weights
    back = load_model(str(path))
    assert back.cfg == model.cfg and not back.training
    for (k, a), (_, b) in zip(model.state_dict().items(), back.state_dict().items()):
        assert torch.equal(a, b), k


def test_missing_file(tmp_path):
    with pytest.raises(WeightsError, match="no such weights file") as err:
        load_model(str(tmp_path / "none.safetensors"))
    _one_line(err)


def test_truncated_file(weights, tmp_path):
    _, path = weights
    data = path.read_bytes()
    bad = tmp_path / "cut.safetensors"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(WeightsError, match="not a readable safetensors") as err:
        load_model(str(bad))
    assert str(bad) in _one_line(err)


def test_foreign_files(tmp_path):
    npz = tmp_path / "x.safetensors"
    np.savez(npz, a=np.zeros(3))
    with pytest.raises(WeightsError) as err:
        load_model(str(npz))
    _one_line(err)
    from safetensors.torch import save_file

    other = tmp_path / "other.safetensors"
    save_file({"w": torch.zeros(3)}, str(other))
    with pytest.raises(WeightsError, match="not corner-detector weights") as err:
        load_model(str(other))


def test_wrong_shapes(weights, tmp_path):
    model, path = weights
    from safetensors.torch import safe_open, save_file

    with safe_open(str(path), framework="pt") as fh:
        meta = fh.metadata()
        tensors = {k: fh.get_tensor(k) for k in fh.keys()}
    tensors["line_mlp.0.weight"] = torch.zeros(3, 3)
    bad = tmp_path / "shape.safetensors"
    save_file(tensors, str(bad), metadata=meta)
    with pytest.raises(WeightsError, match="line_mlp.0.weight") as err:
        load_model(str(bad))
    _one_line(err)
    del tensors["line_mlp.0.weight"]
    save_file(tensors, str(bad), metadata=meta)
    with pytest.raises(WeightsError, match="missing") as err:
        load_model(str(bad))


def test_optimizer_state_refuses_pickled_objects(tmp_path):
    opt = torch.optim.AdamW([torch.nn.Parameter(torch.ones(2))])
    good = tmp_path / "opt.pt"
    save_tensors(str(good), opt.state_dict())
    assert load_tensors(str(good))["param_groups"][0]["lr"] == opt.param_groups[0]["lr"]
    evil = tmp_path / "evil.pt"
    torch.save({"x": _Evil()}, str(evil))
    with pytest.raises(WeightsError, match="holds Python objects besides tensors; refused") as err:
        load_tensors(str(evil))
    _one_line(err)
    assert "weights_only" not in str(err.value) and "trust" not in str(err.value)  # torch's offer to unpickle it
    (tmp_path / "cut.pt").write_bytes(good.read_bytes()[:50])
    with pytest.raises(WeightsError, match="not a readable tensor state"):
        load_tensors(str(tmp_path / "cut.pt"))


class _Evil:
    pass


def test_weights_files_get_the_usual_mode(tmp_path):
    """safetensors' save_file leaves a 0600 file; ours get 0666 & ~umask like every other output."""
    import stat

    from envisat_pose.perception.weights import with_metadata

    old = os.umask(0o022)
    try:
        torch.manual_seed(0)  # this test's untrained model
        path, copy = str(tmp_path / "w.safetensors"), str(tmp_path / "c.safetensors")
        save_weights(path, CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8)))
        with_metadata(path, copy, {"cov_scale": 1.5})
    finally:
        os.umask(old)
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o644
    assert stat.S_IMODE(os.stat(copy).st_mode) == 0o644


def test_the_same_weights_are_the_same_bytes(weights, tmp_path):
    """safetensors writes its metadata map in a random order; the files here do not depend on it: the same model
    saved again, and the same file given the same metadata (with_metadata), are the same bytes, and read back
    (safetensors' own reader) to the same tensors and metadata."""
    import hashlib

    from safetensors.torch import safe_open

    from envisat_pose.perception.weights import with_metadata

    model, path = weights
    digests = set()
    for i in range(4):
        save_weights(str(tmp_path / f"w{i}.safetensors"), model, extra={"cov_scale": 2.0, "b": "x", "a": [1, 2]})
        digests.add(hashlib.sha256((tmp_path / f"w{i}.safetensors").read_bytes()).hexdigest())
        with_metadata(str(path), str(tmp_path / f"m{i}.safetensors"), {"z": "1", "y": "2", "x": "3"})
        digests.add(hashlib.sha256((tmp_path / f"m{i}.safetensors").read_bytes()).hexdigest())
    assert len(digests) == 2
    with safe_open(str(tmp_path / "w0.safetensors"), framework="pt") as f:
        meta = f.metadata()
        assert meta["b"] == "x" and meta["a"] == "[1, 2]" and meta["cov_scale"] == "2.0"
        state = model.state_dict()
        assert set(f.keys()) == set(state) and all(torch.equal(f.get_tensor(k), state[k]) for k in state)
    header_len = int.from_bytes((tmp_path / "w0.safetensors").read_bytes()[:8], "little")
    assert header_len % 8 == 0


def test_with_metadata_drops_the_keys_a_fit_owns_and_returns_them(weights, tmp_path):
    """drop removes the keys a fit owns that it does not write again (returned with their old values); those it
    writes are replaced, and the keys of no fit in drop stay."""
    from envisat_pose.perception.weights import read_metadata, with_metadata

    _, path = weights
    old, new = str(tmp_path / "old.safetensors"), str(tmp_path / "new.safetensors")
    with_metadata(str(path), old, {"cov_scale": 1.5, "error_model": "{}", "face_cue": "cue"})
    removed = with_metadata(old, new, {"cov_scale": 2.0}, drop=("cov_scale", "error_model", "error_model_record"))
    assert removed == {"error_model": "{}"}
    meta = read_metadata(new)
    assert meta["cov_scale"] == "2.0" and meta["face_cue"] == "cue" and "error_model" not in meta
    assert with_metadata(new, new, {"x": 1}) == {} and read_metadata(new)["cov_scale"] == "2.0"
