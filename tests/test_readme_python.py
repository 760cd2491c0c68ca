"""The README's "From Python" example, executed as written (issue 27): the public builders, the tracker on
three frames and track_frames on a folder of frames. The folder it names (my_frames: 20 256 px frames of the
default scenario's camera, blank: as many as the tracker's cold start needs, which track_frames checks as
`envisat track` does) is made here, in a temporary working folder."""

import os
import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def python_examples() -> list[str]:
    text = README.read_text()
    section = text.split("## From Python", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert len(blocks) >= 2, "the section holds the tracking and the training examples"
    return blocks


def python_example() -> str:
    return python_examples()[0]


def test_the_readme_python_example_runs_as_written(tmp_path, monkeypatch, capsys):
    import cv2

    monkeypatch.chdir(tmp_path)
    os.mkdir("my_frames")
    for k in range(20):
        cv2.imwrite(f"my_frames/frame_{k}.png", np.zeros((1024, 1024), np.uint8))  # the MJCF camera's size
    exec(compile(python_example(), str(README), "exec"), {"__name__": "readme"})
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("0.0 acquiring") and "nan" in out[0]
    assert out[-1] == "{'acquiring': 20, 'tracking': 0, 'lost': 0, 'coasting': 0} acquiring"
    assert {"est.npz", "det.npz", "summary.json", "recording.rrd"} <= set(os.listdir("out/mine"))


def test_the_readme_training_example_runs_as_written(tmp_path, monkeypatch, capsys):
    """The training example (issue 41) on the folders it names, made here by `envisat generate`: it trains, writes
    a run folder, detects with its weights and loads every column of det.npz."""
    from envisat_pose.app.cli import main

    monkeypatch.chdir(tmp_path)
    for name, n, seed in (("train", 4, 21), ("heldout", 2, 22)):
        assert main(["generate", "--num-images", str(n), "--shard-size", str(n), "--resolution", "128", "--seed",
                     str(seed), "--out", f"data/{name}", "--quiet"]) == 0
    capsys.readouterr()
    exec(compile(python_examples()[1], str(README), "exec"), {"__name__": "readme"})
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "4 steps"
    assert out[-1].startswith("(2, 8, 2) [")
    assert {"config.json", "checkpoint.safetensors", "state.json", "det.npz"} <= set(os.listdir("runs/det"))


def test_the_readme_adapt_example_names_what_the_library_has():
    """The adapting example (issue 40: minutes of work, run for real by tests/app/test_adapt.py's slow tests)
    compiles, and every name it imports and every argument it passes exist."""
    import inspect

    from envisat_pose.pipelines.adaptation.adapt import adapt
    from envisat_pose.pipelines.runs.track import track_frames

    code = python_examples()[2]
    compile(code, str(README), "exec")
    assert "from envisat_pose.pipelines.adaptation.adapt import AdaptConfig, adapt" in code
    assert {"camera"} <= set(inspect.signature(adapt).parameters)
    assert {"camera", "out_dir"} <= set(inspect.signature(track_frames).parameters)
