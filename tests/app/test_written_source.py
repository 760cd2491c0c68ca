"""Every job's written config names the source that made it under its first line: the package's version and the
commit (what a rerun months later needs beside the config's values). The expected commit is read here from git
itself, not from the code under test."""

import os
import subprocess
from importlib import metadata

import pytest

from envisat_pose.app.cli import main

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _expected_commit() -> str:
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, timeout=10)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, timeout=10)
    except OSError:  # no git here: the copy's commit as its maker gave it, else unknown
        return os.environ.get("ENVISAT_SOURCE_GIT", "").strip() or "unknown"
    if head.returncode != 0:
        return os.environ.get("ENVISAT_SOURCE_GIT", "").strip() or "unknown"
    return head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")


JOBS = {
    "simulate": (["simulate", "--duration-s", "10", "--out", "{d}/run.npz"], "run.config.toml"),
    "estimate": (["estimate", "--scenario", "default", "--duration-s", "10", "--runs", "1", "--out", "{d}/est.npz"],
                 "est.config.toml"),
    "montecarlo": (["montecarlo", "--scenario", "default", "--duration-s", "20", "--runs", "2", "--out", "{d}/mc"],
                   "mc/montecarlo.config.toml"),
    "generate": (["generate", "--num-images", "2", "--resolution", "64", "--out", "{d}/data"],
                 "data/generate.config.toml"),
    # a rate sweep (`envisat montecarlo --rates-hz`): its folder's config, which `--config` reruns
    "sweep": (["montecarlo", "--scenario", "default", "--duration-s", "20", "--runs", "2", "--rates-hz", "1",
               "--out", "{d}/sweep"], "sweep/montecarlo.config.toml"),
}


@pytest.mark.parametrize("verb", sorted(JOBS))
def test_a_written_config_names_the_version_and_commit_that_made_it(verb, tmp_path):
    argv, written = JOBS[verb]
    assert main([a.format(d=tmp_path) for a in argv] + ["--quiet"]) == 0
    lines = (tmp_path / written).read_text().splitlines()
    assert lines[0].startswith(f"# envisat {argv[0]}: the full validated config")
    assert lines[1] == f"# source: envisat-pose {metadata.version('envisat-pose')}, commit {_expected_commit()}"


def _committed_copy(repo, folder: str, add: str) -> str:
    """provenance.py copied to repo/folder/provenance.py in a new git repository whose first commit adds `add`;
    the copy's path (the test skipped where no git is here to make it)."""
    import shutil

    (repo / folder).mkdir(parents=True)
    copy = repo / folder / "provenance.py"
    shutil.copy(os.path.join(ROOT, "envisat_pose", "provenance.py"), copy)
    env = {**os.environ, "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
           "GIT_COMMITTER_EMAIL": "t@t"}
    try:
        for cmd in (["git", "init", "-q"], ["git", "add", add], ["git", "commit", "-q", "-m", "first"]):
            subprocess.run(cmd, cwd=repo, check=True, env=env, capture_output=True)
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("no git here to make a repository")
    return str(copy)


def test_a_copy_in_another_projects_repository_names_no_commit_of_that_project(tmp_path, monkeypatch):
    """An installed copy in a folder another repository tracks (a virtual environment inside a user's project)
    read that project's commit as ours."""
    import importlib.util
    monkeypatch.delenv("ENVISAT_SOURCE_GIT", raising=False)
    repo = tmp_path / "their_project"
    repo.mkdir()
    (repo / "README").write_text("theirs\n")
    copy = _committed_copy(repo, "venv/envisat_pose", "README")  # their file committed, ours not
    spec = importlib.util.spec_from_file_location("copied_provenance", copy)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.git_hash() == "unknown"


def test_reading_the_commit_writes_nothing_in_the_checkout(tmp_path):
    """git_hash ran `git status`, which rewrites a stale index; a job under `ulimit -f` had git killed mid-write
    (SIGXFSZ), leaving an index.lock that blocked every later git command in the checkout."""
    import sys

    repo = tmp_path / "checkout"
    copy = _committed_copy(repo, "envisat_pose", ".")
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True).stdout.strip()
    os.utime(copy, (1e9, 1e9))  # the index's stat data stale: a plain `git status` would rewrite the index
    script = ("import importlib.util, resource, sys\n"
              "resource.setrlimit(resource.RLIMIT_FSIZE, (16, 16))\n"
              f"spec = importlib.util.spec_from_file_location('copied_provenance', {str(copy)!r})\n"
              "module = importlib.util.module_from_spec(spec)\n"
              "spec.loader.exec_module(module)\n"
              "print(module.git_hash())\n")
    env = {k: v for k, v in os.environ.items() if k != "ENVISAT_SOURCE_GIT"}
    out = subprocess.run([sys.executable, "-B", "-c", script], capture_output=True, text=True, env=env, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == head  # the file's content unchanged: not dirty
    assert not (repo / ".git" / "index.lock").exists()
    assert subprocess.run(["git", "status", "--porcelain"], cwd=repo, capture_output=True).returncode == 0
