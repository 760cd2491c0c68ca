"""A shard the disk stops taking (a full disk; `ulimit -f`, EFBIG, stands for it in a child process, as
tests/analysis/test_recording_no_room.py does): the writer removes its temporary file at once and its error names
the shard (tarfile's writes name no file: the line said only 'File too large'); a generate whose workers stop
leaves no partial shard of theirs (each one's, a killed sibling's: they stayed until a rerun), keeps the shards
finished before, and the same command finishes the dataset once there is room."""

import json
import os
import resource
import subprocess
import sys

os.environ.setdefault("MUJOCO_GL", "osmesa")

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CLI = [sys.executable, "-m", "envisat_pose.app.cli"]
LIMIT_BYTES = 20_000  # a shard of 2 images at 256 px is ~80 kB; the manifest and the config ~3 kB


def env() -> dict:
    return {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (ROOT, os.environ.get("PYTHONPATH")) if p)}


def limit_file_size() -> None:
    """In the child before it runs: no file past LIMIT_BYTES (Python ignores SIGXFSZ: the write fails, EFBIG)."""
    resource.setrlimit(resource.RLIMIT_FSIZE, (LIMIT_BYTES, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))


WRITER = r"""
import json, os, sys
from envisat_pose.datagen.shards import ShardWriter

out = sys.argv[1]
try:
    with ShardWriter(os.path.join(out, "shard-000000.tar")) as writer:
        for k in range(8):
            writer.write(f"{k:09d}", {"png": os.urandom(10_000)})
    print(json.dumps({"raised": None}))
except OSError as err:  # the writer's frame still held: what it left is what a stopped worker leaves
    print(json.dumps({"raised": err.errno, "filename": err.filename, "left": sorted(os.listdir(out))}))
"""


def test_a_shard_the_disk_stops_taking_leaves_no_temporary_file_and_its_error_names_the_shard(tmp_path):
    import errno

    done = subprocess.run([sys.executable, "-c", WRITER, str(tmp_path)], capture_output=True, text=True,
                          env=env(), cwd=tmp_path, preexec_fn=limit_file_size)
    assert done.returncode == 0, done.stderr[-2000:]
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got == {"raised": errno.EFBIG, "filename": str(tmp_path / "shard-000000.tar"), "left": []}, got


def test_generate_on_a_full_disk_is_one_line_and_leaves_no_partial_shard(tmp_path):
    out = tmp_path / "ds"
    cmd = CLI + ["generate", "--num-images", "6", "--shard-size", "2", "--resolution", "256", "--seed", "4",
                 "--workers", "2", "--quiet", "--out", str(out)]
    first = subprocess.run(cmd, capture_output=True, text=True, env=env(), cwd=tmp_path)
    assert first.returncode == 0, first.stderr[-2000:]
    whole = {n: (out / n).read_bytes() for n in os.listdir(out)}
    for name in ("shard-000001.tar", "shard-000002.tar"):  # to be redone by the resume, on a full disk
        os.remove(out / name)
    full = subprocess.run(cmd, capture_output=True, text=True, env=env(), cwd=tmp_path, preexec_fn=limit_file_size)
    err = full.stderr.strip().splitlines()
    assert full.returncode == 1 and len(err) == 1, full.stderr[-2000:]
    assert err[0].startswith("envisat generate: error: File too large writing ") and "shard-00000" in err[0], err
    assert sorted(os.listdir(out)) == ["generate.config.toml", "manifest.json", "shard-000000.tar"]  # no partial
    assert (out / "shard-000000.tar").read_bytes() == whole["shard-000000.tar"]  # the finished shard kept
    again = subprocess.run(cmd, capture_output=True, text=True, env=env(), cwd=tmp_path)
    assert again.returncode == 0 and "2 images already there" in again.stdout, again.stderr[-2000:]
    assert {n: (out / n).read_bytes() for n in os.listdir(out)} == whole
