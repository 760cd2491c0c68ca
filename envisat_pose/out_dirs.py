"""The one output-folder rule of every job: `check_out_dir` (creating nothing) and `make_out_dir` (create, parents
too, prove writable by a real write); for an output file, `check_out_file` and `make_out_file_dir(s)` (its
folder). A file on the path is one InputError naming the field and the path.
"""

from __future__ import annotations

import contextlib
import os
import warnings
from typing import Sequence

from envisat_pose.config import InputError
from envisat_pose.png_marks import JOB_KEY, written_png

PARTIAL_PREFIX = ".tmp-"  # io.atomic_path's temporary files: what a killed writer leaves behind


def _file_in_the_way(path: str) -> str | None:
    """The existing path at or above `path` that is not a folder (a file where a folder must be), or None; named
    as the user named path (relative stays relative)."""
    here = os.path.abspath(path)
    while not os.path.lexists(here):
        if os.path.dirname(here) == here:
            return None
        here = os.path.dirname(here)
    if os.path.isdir(here):
        return None
    return here if os.path.isabs(path) else os.path.relpath(here)


def _refuse_empty(path: str, field: str, kind: str) -> None:
    """An empty path (`--out ""`, an unset variable in a script) names nothing: os.path.abspath reads it as the
    working folder, which passed the checks: the job failed only at its first write (dataset export after exporting
    every image)."""
    if not path:
        raise InputError(f"{field} '': expected a {kind} path (an empty one names none)")


def check_out_dir(out_dir: str, parents: bool = True, field: str = "out_dir") -> None:
    """Check, creating nothing, that out_dir is a folder or can become one: nothing on its path is a file (out_dir
    itself, or a folder above it); without parents, its parent must exist too. InputError naming the field."""
    _refuse_empty(out_dir, field, "folder")
    blocker = _file_in_the_way(out_dir)
    if blocker is not None:
        where = "exists and is not a folder" if os.path.abspath(blocker) == os.path.abspath(out_dir) else \
            f"{blocker!r} is a file, not a folder"
        raise InputError(f"{field} {out_dir!r}: {where}; expected a folder (or a path where one can be made)")
    parent = os.path.dirname(os.path.abspath(out_dir))
    if not parents and not os.path.isdir(parent):
        raise InputError(f"{field} {out_dir!r}: parent folder {parent!r} does not exist")


def check_makeable(out_dir: str, field: str = "out_dir") -> None:
    """check_out_dir, then prove that out_dir can be made, leaving nothing: a probe folder made and removed in the
    nearest folder on its path that exists (out_dir itself where it does). For a job whose folder appears later
    (a training run's with its first step): /proc or a read-only disk refused before any work. InputError."""
    import tempfile

    check_out_dir(out_dir, True, field)
    place = os.path.abspath(out_dir)
    while not os.path.isdir(place):
        place = os.path.dirname(place)
    try:
        os.rmdir(tempfile.mkdtemp(prefix=PARTIAL_PREFIX + "probe-", dir=place))
    except OSError as err:
        raise InputError(f"{field} {out_dir!r}: cannot be made or written ({err.strerror or err} in {place!r})") \
            from None


def make_out_dir(out_dir: str, subdirs: Sequence[str] = (), parents: bool = True, field: str = "out_dir") -> None:
    """check_out_dir, then create out_dir (its parents too, and its subdirs) and prove it writable by writing
    (and removing) a probe file in it.

    os.access says yes to root everywhere (even /proc), so only a real write tells; any OSError becomes one
    InputError line naming the folder and the system's reason.
    """
    check_out_dir(out_dir, parents, field)
    reason = _made_writable([out_dir, *(os.path.join(out_dir, s) for s in subdirs)])
    if reason:
        raise InputError(f"{field} {out_dir!r}: cannot write there ({reason})")


@contextlib.contextmanager
def made_out_dir(out_dir: str, parents: bool = True, field: str = "out_dir"):
    """make_out_dir for a job's block: a folder this call made is removed again, with the parents it made, when
    the block fails or is interrupted and leaves them empty (a folder that was there stays, whatever it holds)."""
    made, folder = [], os.path.abspath(out_dir)
    while not os.path.exists(folder):
        made.append(folder)
        folder = os.path.dirname(folder)
    make_out_dir(out_dir, parents=parents, field=field)
    try:
        yield
    except BaseException:
        for folder in made:  # deepest first
            with contextlib.suppress(OSError):
                os.rmdir(folder)  # only an empty one
        raise


def _made_writable(folders: list[str]) -> str | None:
    """Make the folders (parents too) and write and remove a probe file in the first; the system's reason when
    that fails, else None."""
    import tempfile

    try:
        for folder in folders:
            os.makedirs(folder, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=PARTIAL_PREFIX + "probe-", dir=folders[0])
        try:
            os.write(fd, b"probe")
        finally:
            os.close(fd)
            os.remove(probe)
    except OSError as err:
        return str(err.strerror or err)
    return None


def check_out_file(path: str, field: str = "out", inputs: str | Sequence[str] = (),
                   inputs_field: str = "data") -> None:
    """Check, creating nothing, that an output file can be written at path: it is not a folder, nothing above
    it is a file (its missing folders are made by make_out_file_dir when the job writes) and it lies inside none
    of the input folders `inputs` (a dataset read: its manifest once overwritten by `evaluate --json`). InputError."""
    _refuse_empty(path, field, "file")
    if os.path.isdir(path):
        raise InputError(f"{field} {path!r} is a folder; expected a file path")
    for folder in [inputs] if isinstance(inputs, (str, os.PathLike)) else inputs:
        if os.path.isdir(folder) and os.path.commonpath([os.path.realpath(path), os.path.realpath(folder)]) == \
                os.path.realpath(folder):
            raise InputError(f"{field} {path!r} lies inside `{inputs_field}` {os.fspath(folder)!r}: expected an "
                             "output apart from the input folder (its files are not the job's to replace)")
    blocker = _file_in_the_way(os.path.dirname(path) or ".")
    if blocker is not None:
        raise InputError(f"{field} {path!r}: {blocker!r} is a file, not a folder; expected a file path in a folder "
                         "(or where one can be made)")


def make_out_file_dir(path: str, field: str = "out") -> None:
    """check_out_file, then make the output file's folder (parents too) and prove it writable (make_out_dir)."""
    check_out_file(path, field)
    folder = os.path.dirname(os.path.abspath(path))
    reason = _made_writable([folder])
    if reason:
        raise InputError(f"{field} {path!r}: cannot write in its folder {folder!r} ({reason})")


def make_out_file_dirs(outputs: dict[str, str]) -> None:
    """Every output file {path: field} checked (check_out_file), then their folders made (make_out_file_dir):
    nothing is made unless every one can be written."""
    for path, name in outputs.items():
        check_out_file(path, name)
    for path, name in outputs.items():
        make_out_file_dir(path, name)


def refuse_overlap(out_dir: str, source: str | None, field: str = "out_dir", source_field: str = "source") -> None:
    """InputError in one line when the output folder out_dir is the input folder `source`, lies inside it or holds
    it (real paths compared: links followed): the job would write among the user's input files, and a rerun,
    replacing its own outputs, could remove them. A source that is not a folder (a video file) or None passes."""
    if not source or not os.path.isdir(source):
        return
    out, src = os.path.realpath(out_dir), os.path.realpath(source)
    common = os.path.commonpath([out, src])
    if common not in (out, src):
        return
    how = "is" if out == src else "lies inside" if common == src else "holds"
    raise InputError(f"{field} {out_dir!r} {how} `{source_field}` {source!r}: expected an output folder apart "
                     "from the input (its files are not the job's to write among or replace); use another folder")


def written_by(path: str, job: str) -> bool:
    """Whether `path` is a config file a job `envisat JOB` wrote: its first line '# envisat JOB: ...'."""
    try:
        with open(path, encoding="utf-8") as fh:
            return fh.readline().startswith(f"# envisat {job}:")
    except (OSError, UnicodeDecodeError):
        return False


def refuse_foreign_outputs(out_dir: str, names, config_name: str, job: str, field: str = "out_dir") -> None:
    """InputError in one line, before any work, when out_dir holds an entry at one of the job's output file names
    (which a run replaces, or removes when it does not write it again) that is not an earlier run's: out_dir holds
    no config_name written by `envisat JOB` (written_by), so the entries are another's (a user's summary.json), or
    the entry is a folder (where the job's file goes; a link is replaced, not what it names)."""
    if not os.path.isdir(out_dir):
        return
    present = [n for n in names if os.path.lexists(os.path.join(out_dir, n))]
    odd = [n for n in present if os.path.isdir(os.path.join(out_dir, n)) and not os.path.islink(os.path.join(
        out_dir, n))]
    if odd:
        raise InputError(f"{field} {out_dir!r} holds a folder {odd[0]!r} where the job's file {odd[0]} goes; move it "
                         "out or use another folder")
    if present and not written_by(os.path.join(out_dir, config_name), job):
        shown = ", ".join(present[:3]) + (", ..." if len(present) > 3 else "")
        raise InputError(f"{field} {out_dir!r} holds {shown} but no {config_name} of an earlier `envisat {job}`: not "
                         "its outputs to replace; move them out or use another folder")


def own_side_files(out: str, config: str, plot_png: str, job: str, plot: bool, field: str = "out") -> list[str]:
    """Check, before any work, the files a one-file job writes beside its output `out`: its config (replaced) and
    its plot (replaced with plot, else removed as a stale one). Either may be replaced only where an earlier
    `envisat JOB` wrote it (the config's first line, written_by; the PNG's mark, png_marks.written_png, or the
    job's own config beside it, for a plot written before the mark): a user's file of that name is refused in one
    InputError line naming it; a user's PNG where no plot is written is left alone, said in a warning. Returns
    the names (in out's folder) the job may remove when it writes no plot."""
    if os.path.lexists(config) and not written_by(config, job):
        raise InputError(f"{field} {out!r}: its config goes to {config!r}, which holds a file no `envisat {job}` "
                         f"wrote (its first line is not '# envisat {job}: ...'): not the job's to replace; move it "
                         f"or use another {field}")
    # a PNG beside the job's own config is its earlier plot, marked or not (plots written before the mark carry none)
    beside_own_config = os.path.lexists(config) and written_by(config, job)
    if not os.path.lexists(plot_png) or written_png(plot_png, job) or beside_own_config:
        return [os.path.basename(plot_png)]
    whose = f"a PNG no `envisat {job}` wrote (no {JOB_KEY!r} mark naming it)"
    if plot:
        raise InputError(f"{field} {out!r}: its plot goes to {plot_png!r}, {whose}: not the job's to replace; "
                         f"move it or use another {field}")
    warnings.warn(f"left {plot_png!r} alone: {whose}, so not an earlier plot of this output to remove", stacklevel=3)
    return []
