"""`envisat adapt`'s after/ track names the weights the job leaves: RUN_DIR/detector.safetensors when adopted, a line
saying they were not kept otherwise; never the candidate inside the job's stage folder, which is gone once the job
ends (after/track.config.toml once named '.tmp-stage-.../round-0.safetensors': a rerun from it found no file). The
job runs here with its steps faked: no frames, no network."""

import json
import os
import shutil
import types

import numpy as np
import pytest

from envisat_pose.pipelines.adaptation.adapt import AdaptConfig
from envisat_pose.pipelines.common.job_defaults import weights_name
from envisat_pose.status import TRACKING

T = 40


def fake_track(tcfg, source, camera, remap, out_dir, progress=False):
    """A track run's records, naming its weights as track_frames does; the candidate tracks 1 cm off the base
    (a change: the verdict adopts it), unless the test says the candidate changes nothing."""
    os.makedirs(out_dir)
    name = weights_name(tcfg.weights)
    x = np.zeros((1, T, 12)) + (0.01 if "round-" in tcfg.weights and fake_track.moves else 0.0)
    P = np.broadcast_to(np.eye(12), (1, T, 12, 12))
    np.savez(os.path.join(out_dir, "est.npz"), t_s=np.arange(T, dtype=float), x_hat=x, P=P,
             status=np.full((1, T), TRACKING), nis=np.full((1, T), 16.0), nis_dof=np.full((1, T), 16),
             config_json=np.array(json.dumps({"track": {"weights": name}})))
    np.savez(os.path.join(out_dir, "det.npz"), n_hypotheses=np.ones(T, dtype=int),
             config_json=np.array(json.dumps({"weights": name})))
    with open(os.path.join(out_dir, "summary.json"), "w") as f:
        json.dump({"weights": name, "weights_sha256": "ab" * 32}, f)
    with open(os.path.join(out_dir, "track.config.toml"), "w") as f:
        f.write(f'# envisat track\nscenario = "default"\nweights = {json.dumps(name)}\nthreads = 1\n')


@pytest.mark.parametrize("moves", [True, False])
def test_the_after_track_names_the_weights_the_job_leaves(monkeypatch, tmp_path, detector_weights, moves):
    import envisat_pose.pipelines.adaptation.adapt as adapt_module
    from envisat_pose.pipelines.adaptation.run_records import NOT_KEPT

    lab = {"frames": np.arange(3), "trusted": 3, "sigma_px": np.ones(3), "edges": {}, "labels": [{}] * 3}
    fake_track.moves = moves
    monkeypatch.setattr(adapt_module, "label_step", lambda run, d: (lab, [np.zeros((8, 8), np.uint8)] * 3))
    monkeypatch.setattr(adapt_module, "fine_tune", lambda *a, **k: ("model", {}))
    monkeypatch.setattr(adapt_module, "save_adapted", lambda model, base, path, extra: shutil.copy(base, path) or True)
    monkeypatch.setattr(adapt_module, "recalibration_step", lambda *a, **k: {})
    monkeypatch.setattr(adapt_module, "track_frames", fake_track)
    frame = tmp_path / "frame.png"
    frame.write_bytes(b"frame")
    source = types.SimpleNamespace(t_s=np.arange(T, dtype=float), path="frames", kind="images", size_px=(8, 8),
                                   files=[str(frame)], bit_depth=12)
    cfg = AdaptConfig()
    tcfg = adapt_module.TrackConfig(weights=detector_weights)
    out = tmp_path / "run"
    stage = out / ".tmp-stage-1-x"
    stage.mkdir(parents=True)
    report = adapt_module._adapt(cfg, tcfg, source, None, None, str(stage), False, ["envisat", "adapt"])
    assert report["adopted"] is moves
    want = str(out / "detector.safetensors") if moves else NOT_KEPT
    after = stage / "after"
    assert json.loads((after / "summary.json").read_text())["weights"] == want
    assert f"weights = {json.dumps(want)}\n" in (after / "track.config.toml").read_text()
    with np.load(after / "est.npz") as est, np.load(after / "det.npz") as det:
        assert json.loads(str(est["config_json"]))["track"]["weights"] == want
        assert json.loads(str(det["config_json"]))["weights"] == want
        assert det["n_hypotheses"].shape == (T,)  # the other arrays as they were
    assert json.loads((stage / "before" / "summary.json").read_text())["weights"] == weights_name(detector_weights)
    assert (stage / "detector.safetensors").exists() is moves
    assert report["source"]["bit_depth"] == 12  # 16-bit files of 12-bit data: how the frames were read


def test_the_adapted_weights_say_what_they_were_adapted_on(monkeypatch, tmp_path, detector_weights):
    """The candidate's metadata records the frames (by content), the base weights and the job's settings, even
    where the recalibration measured nothing to write (once the file then carried only the base's metadata:
    nothing in detector.safetensors said it was adapted, or on what)."""
    import envisat_pose.pipelines.adaptation.adapt as adapt_module
    from envisat_pose.perception.weights import load_model, read_metadata
    from envisat_pose.perception.weights_keys import ADAPTATION_KEY

    monkeypatch.setattr(adapt_module, "recalibrate", lambda *a, **k: {"scale": None, "corners": 0})
    monkeypatch.setattr(adapt_module, "decide_scale", lambda *a, **k: None)
    frame = tmp_path / "frame.png"
    frame.write_bytes(b"frame")
    source = types.SimpleNamespace(t_s=np.arange(T, dtype=float), path="frames", kind="images", size_px=(8, 8),
                                   files=[str(frame)], bit_depth=12)
    cfg = AdaptConfig(params="norm_heads", steps=3)
    run = adapt_module.AdaptRun(cfg, adapt_module.TrackConfig(weights=detector_weights), source, None, None,
                                str(tmp_path), False, 30, (), {})
    candidate = str(tmp_path / "round-0.safetensors")
    shutil.copy(detector_weights, candidate)
    lab = {"edges": {}, "labels": [{}] * 3}
    adapt_module.recalibration_step(run, detector_weights, candidate, load_model(detector_weights),
                                    [np.zeros((8, 8), np.uint8)] * 3, lab)
    record = json.loads(read_metadata(candidate)[ADAPTATION_KEY])
    assert record["source"]["content_sha256"] == adapt_module.content_sha256(source)
    assert record["source"]["path"] == "frames" and record["source"]["frames"] == T
    assert record["source"]["bit_depth"] == 12
    assert record["base_weights"] == weights_name(detector_weights) and len(record["base_sha256"]) == 64
    assert record["held_out_from_frame"] == 30 and record["params"] == "norm_heads" and record["steps"] == 3
