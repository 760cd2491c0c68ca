"""The README's "From Python" example, executed as written (issue 27): the public builders, the tracker on
three frames and track_frames on a folder of frames. The folder it names (my_frames: 20 256 px frames of the
default scenario's camera, blank: as many as the tracker's cold start needs, which track_frames checks as
`envisat track` does) is made here, in a temporary working folder."""

import os
import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def python_example() -> str:
    text = README.read_text()
    section = text.split("## From Python", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 1, "the section holds one Python example"
    return blocks[0]


def test_the_readme_python_example_runs_as_written(tmp_path, monkeypatch, capsys):
    import cv2

    monkeypatch.chdir(tmp_path)
    os.mkdir("my_frames")
    for k in range(20):
        cv2.imwrite(f"my_frames/frame_{k}.png", np.zeros((256, 256), np.uint8))
    exec(compile(python_example(), str(README), "exec"), {"__name__": "readme"})
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("0.0 acquiring") and "nan" in out[0]
    assert out[-1] == "{'acquiring': 20, 'tracking': 0, 'lost': 0, 'coasting': 0} acquiring"
    assert {"est.npz", "det.npz", "summary.json", "recording.rrd"} <= set(os.listdir("out/mine"))
