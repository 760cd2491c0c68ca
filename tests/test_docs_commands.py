"""The commands and Python names the README and docs/ show a new user, checked against the code: every `envisat
VERB` named is a verb, every `--flag` written after it is one of that verb's (or sub-verb's) flags, every command
of a shell block parses with the real parser as written (types, choices, required flags), every
`envisat_pose.x.y` name and `from envisat_pose... import` name resolves, and every TOML block is TOML. Nothing is
run: tests/test_readme_python.py runs the README's Python examples. The checker reads text, so a test shows it
catching planted mistakes."""

import argparse
import contextlib
import importlib
import io
import re
import shlex
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ("README.md", "docs/usage.md", "docs/formats.md", "docs/design.md", "docs/reference.md")
# what the README's shell variables stand for (`T=models/upper_stage.xml`; usage.md's `for s in paper-...`)
SHELL_VARS = {"$T": "models/upper_stage.xml", "$s": "paper-all-0.02"}
FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")


def subparsers(parser: argparse.ArgumentParser) -> dict:
    return next((a.choices for a in parser._actions if isinstance(a, argparse._SubParsersAction)), {})


@pytest.fixture(scope="module")
def parser() -> argparse.ArgumentParser:
    from envisat_pose.app.cli import build_parser

    return build_parser()


def block_commands(text: str) -> list[str]:
    """Each `envisat ...` command of the text's shell blocks: continuations joined, comments dropped, split at
    `&&` and `;`, the shell variables above put in."""
    out = []
    for block in re.findall(r"```(?:bash|sh|console|shell)\n(.*?)```", text, flags=re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = re.sub(r"(^|\s)#.*", "", line)
            for name, value in SHELL_VARS.items():
                line = line.replace(name, value)
            out += [c.strip() for c in re.split(r"&&|;", line) if c.strip().startswith("envisat ")]
    return out


def inline_commands(text: str) -> list[str]:
    """Each `envisat ...` in an inline code span (prose, tables), as written."""
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    return [c for c in re.findall(r"`(envisat [^`]+)`", text)]


def flag_mistakes(commands: list[str], parser: argparse.ArgumentParser) -> list[str]:
    """A line per command naming a verb that is not one, or a flag its verb (or sub-verb) does not take."""
    verbs = subparsers(parser)
    out = []
    for cmd in commands:
        words = cmd.split()
        if len(words) < 2 or not re.fullmatch(r"[a-z][a-z-]*", words[1]) or words[1].isupper():
            continue  # `envisat VERB`, `envisat --help`: a placeholder, not a verb
        verb = verbs.get(words[1])
        if verb is None:
            out.append(f"{cmd!r}: no verb {words[1]!r} (verbs: {', '.join(verbs)})")
            continue
        sub = subparsers(verb)
        if len(words) > 2 and words[2] in sub:
            verb = sub[words[2]]
        known = {o for a in verb._actions for o in a.option_strings}
        out += [f"{cmd!r}: {words[1]} has no flag {f}" for f in FLAG.findall(cmd) if f not in known]
    return out


def parse_mistakes(commands: list[str], parser: argparse.ArgumentParser) -> list[str]:
    """A line per whole command (no `[optional]` or `a|b` placeholders) the real parser refuses, with its reason."""
    out = []
    for cmd in commands:
        if re.search(r"[\[|]", cmd):
            continue
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                parser.parse_args(shlex.split(cmd)[1:])
        except SystemExit:
            out.append(f"{cmd!r}: {err.getvalue().strip().splitlines()[-1]}")
    return out


def resolves(dotted: str) -> bool:
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for part in parts[i:]:
            if not hasattr(obj, part):
                return False
            obj = getattr(obj, part)
        return True
    return False


def python_names(text: str) -> list[str]:
    """Every dotted `envisat_pose.x.y` name and every name a `from envisat_pose... import` line imports."""
    names = [m.rstrip(".") for m in re.findall(r"\benvisat_pose(?:\.[A-Za-z_]\w*)+", text)]
    for module, imported in re.findall(r"from (envisat_pose[\w.]*) import ([\w, ]+)", text):
        names += [f"{module}.{n.strip()}" for n in imported.split(",") if n.strip()]
    return names


def read(name: str) -> str:
    return (ROOT / name).read_text(encoding="utf-8")


@pytest.mark.parametrize("doc", DOCS)
def test_every_verb_and_flag_the_docs_name_exists(doc, parser):
    text = read(doc)
    assert flag_mistakes(block_commands(text) + inline_commands(text), parser) == []


@pytest.mark.parametrize("doc", DOCS)
def test_every_command_of_the_docs_shell_blocks_parses_as_written(doc, parser):
    assert parse_mistakes(block_commands(read(doc)), parser) == []


@pytest.mark.parametrize("doc", DOCS)
def test_every_python_name_the_docs_give_resolves(doc):
    assert [n for n in python_names(read(doc)) if not resolves(n)] == []


@pytest.mark.parametrize("doc", DOCS)
def test_every_toml_block_of_the_docs_is_toml(doc):
    for block in re.findall(r"```toml\n(.*?)```", read(doc), flags=re.S):
        tomllib.loads(block)


def test_the_docs_show_commands_of_most_verbs(parser):
    """The extraction finds what it should (a regex that matched nothing would pass every test above)."""
    shown = {c.split()[1] for doc in DOCS for c in block_commands(read(doc)) + inline_commands(read(doc))}
    assert set(subparsers(parser)) <= shown
    assert len(block_commands(read("README.md"))) >= 10


def test_the_checker_catches_planted_mistakes(parser):
    text = ("```bash\nenvisat simulate --duration 600 --out a.npz   # --plot in a comment is not read\n"
            "envisat estimate --truth a.npz \\\n    --runs thirty --out e.npz && envisat simulat --out b.npz\n"
            "envisat dataset export data/train --format cocoa --out x\n```\n"
            "Prose: `envisat track --image DIR --out D` and `envisat train [--steps N] --budget-s S`.\n")
    blocks, inline = block_commands(text), inline_commands(text)
    assert len(blocks) == 4 and blocks[1].endswith("--runs thirty --out e.npz") and "--plot" not in blocks[0]
    flags = flag_mistakes(blocks + inline, parser)
    assert [m.split(": ", 1)[1] for m in flags] == [
        "simulate has no flag --duration", "no verb 'simulat' (verbs: " + ", ".join(subparsers(parser)) + ")",
        "track has no flag --image", "train has no flag --budget-s"]
    parsed = parse_mistakes(blocks, parser)  # the parser refuses --duration too (it once read it as --duration-s)
    assert len(parsed) == 4 and "--duration 600" in parsed[0] and "'thirty'" in parsed[1]
    assert "'simulat'" in parsed[2] and "'cocoa'" in parsed[3]
    assert python_names("`envisat_pose.status.legend()`, from envisat_pose import Tracker, Nope") == [
        "envisat_pose.status.legend", "envisat_pose.Tracker", "envisat_pose.Nope"]
    assert resolves("envisat_pose.status.legend") and not resolves("envisat_pose.Nope")
