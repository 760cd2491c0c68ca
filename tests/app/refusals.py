"""The app tests' check of a refusal: a verb given argv exits 2 with one line on stderr holding every word, and
writes nothing at out (imported by the tests of this folder: pytest puts it on the path)."""

import os

from envisat_pose.app.cli import main


def refused(argv, capsys, out, *words) -> str:
    """Run the CLI on argv; assert the refusal (module docstring); return its line."""
    capsys.readouterr()
    assert main(argv) == 2, argv
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and all(w in err for w in words), err
    assert not os.path.exists(out), out
    return err
