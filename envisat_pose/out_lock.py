"""One job at a time on an output: `output_lock` (a context manager) and `locks_output` (its decorator for a job's
function) hold an OS advisory lock (flock) on a lock file while the job runs; a second job on the same output is
refused at once in one InputError line naming the path and the holder's job and pid, having written nothing.

A folder's lock file is LOCK_NAME inside it; a single output file's is `.NAME.envisat.lock` beside it (two jobs
writing two files of one folder do not exclude each other). The kernel holds the lock, not the file: it goes
when the holder's process ends in any way (a crash, SIGKILL), so a lock file a killed job left blocks nothing,
and its text (pid, job, start time) only words the refusal. The holder removes its lock file when the job ends,
while still holding the lock; a job that opened the file just before checks after locking that the path still
names the file it locked, else starts again: an output's folder after a job holds what it held before plus the
job's files. A job locking an output its own thread holds (a job calling another on the same folder) goes on
under the same lock; readers (`envisat view`, `dataset verify`) take no lock. Under torchrun the ranks are one
job: rank 0 holds the lock.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import functools
import inspect
import json
import os
import threading
import time

from envisat_pose.config import InputError
from envisat_pose.out_dirs import check_out_dir, check_out_file
from envisat_pose.pools import torchrun_int

LOCK_NAME = ".envisat.lock"  # a locked output folder's lock file; an output file's: '.NAME' + LOCK_NAME beside it
_held: dict[str, list] = {}  # this process's locks: lock file's real path -> [thread id, depth, pid, descriptor]


def _close_inherited() -> None:
    """In a child forked while a lock is held (a DataLoader worker): its copy of each lock's descriptor closed, so
    the lock goes with the job's own process (a SIGKILLed job's forked workers would hold it until they end); the
    parent's descriptor keeps the lock (flock's lock is the open file's, released when its last descriptor goes)."""
    for entry in list(_held.values()):
        try:
            os.close(entry[3])
        except OSError:
            pass
    _held.clear()


os.register_at_fork(after_in_child=_close_inherited)


def lock_file(path: str, folder: bool = True) -> str:
    """The lock file of the output `path`: a folder's LOCK_NAME inside it, a file's `.NAME.envisat.lock` beside it."""
    path = os.path.abspath(path)
    if folder:
        return os.path.join(path, LOCK_NAME)
    return os.path.join(os.path.dirname(path), f".{os.path.basename(path)}{LOCK_NAME}")


def is_lock_file(name: str) -> bool:
    """Whether a folder entry's name is a lock file of this module (a listing of a job's folder skips it)."""
    return name.startswith(".") and name.endswith(LOCK_NAME)


def _holder(fd: int) -> str:
    """The holder's job, pid and start as its lock file says ('another job' when the text is not there yet)."""
    try:
        text = json.loads(os.pread(fd, 4096, 0).decode("utf-8"))
        return f"envisat {text['job']}, pid {int(text['pid'])}, since {text['started']}"
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return "another job"


def _made_folders(folder: str) -> list[str]:
    """The folders on the way to `folder` (itself included) that do not exist yet, deepest first."""
    made, folder = [], os.path.abspath(folder)
    while not os.path.exists(folder):
        made.append(folder)
        folder = os.path.dirname(folder)
    return made


def _open_locked(lock: str, field: str, path: str, what: str) -> int:
    """An open descriptor of `lock` holding its flock; InputError when another process holds it."""
    for _ in range(100):  # another holder may remove the file between our open and our lock: open it again
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        except PermissionError as denied:  # another user's lock file in a shared folder: a read-only one locks too
            try:
                fd = os.open(lock, os.O_RDONLY | os.O_CLOEXEC)
            except FileNotFoundError:
                raise denied from None  # no lock file to share: the folder refuses a new file (its reason, not ENOENT)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            who = _holder(fd)
            os.close(fd)
            if err.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise
            raise InputError(f"{field} {path!r} is in use by another job ({who}); nothing was written: wait for "
                             f"it to end or use another {what}") from None
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(lock))
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)  # we locked a file its holder had removed: the path names another (or none) now
    raise InputError(f"{field} {path!r}: its lock file {lock!r} keeps changing; use another {what}")


def _release(lock: str, fd: int) -> None:
    """Remove the lock file while it is still locked (see the module doc), then let the lock go."""
    with contextlib.suppress(OSError):
        if os.path.samestat(os.fstat(fd), os.stat(lock)):
            os.remove(lock)
    os.close(fd)


@contextlib.contextmanager
def output_lock(path, job: str, *, field: str = "out_dir", folder: bool = True, beside: bool = False):
    """Hold the lock of the output `path` (a folder; folder=False: one output file) for job `job` (the verb's
    name, for the refusal's text) while the block runs. beside: a folder's lock file beside it, as a file's (a job
    that publishes its folder whole by a rename, `dataset export`: the folder is not made before it is complete).
    The path is checked first (out_dirs.check_out_dir / check_out_file: InputError naming `field`), then the
    folder the lock file goes in is made (parents too);
    folders made here are removed again when the block fails and leaves them empty. InputError in one line,
    having written nothing, when another job holds it (see the module doc)."""
    path = os.fspath(path)
    # a torchrun rank besides 0: the job's lock is rank 0's (RANK alone, which other tools set, locks as usual)
    if torchrun_int("WORLD_SIZE", 1) > 1 and torchrun_int("RANK", 0) != 0:
        yield
        return
    (check_out_dir if folder else check_out_file)(path, field=field)
    lock = lock_file(path, folder and not beside)
    where = os.path.dirname(lock)
    key = os.path.join(os.path.realpath(where), os.path.basename(lock))
    mine = _held.get(key)
    if mine is not None and mine[2] == os.getpid() and mine[0] == threading.get_ident():
        mine[1] += 1  # this thread's job already holds it (one job calling another on the same output)
        try:
            yield
        finally:
            mine[1] -= 1
        return
    made = _made_folders(where)
    try:
        os.makedirs(where, exist_ok=True)
        fd = _open_locked(lock, field, path, "folder" if folder else "file")
    except OSError as err:
        _remove_made(made)
        place = "there" if folder and not beside else f"in its folder {where!r}"  # make_out_dir's, make_out_file_dir's
        raise InputError(f"{field} {path!r}: cannot write {place} ({err.strerror or err})") from None
    except BaseException:
        _remove_made(made)
        raise
    with contextlib.suppress(OSError):  # the refusal's text for a second job (a read-only descriptor: none)
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps({"pid": os.getpid(), "job": job, "started": time.strftime(
            "%Y-%m-%d %H:%M:%S")}).encode("utf-8"), 0)
    _held[key] = [threading.get_ident(), 1, os.getpid(), fd]
    try:
        yield
    except BaseException:
        _held.pop(key, None)
        _release(lock, fd)
        _remove_made(made)
        raise
    _held.pop(key, None)
    _release(lock, fd)


def _remove_made(made: list[str]) -> None:
    for folder in made:  # deepest first; only an empty one
        with contextlib.suppress(OSError):
            os.rmdir(folder)


def locks_output(arg: str, job: str, *, folder: bool = True, field: str | None = None, beside: bool = False):
    """Decorator: the job's function runs under output_lock of its argument `arg` (by name or position; its
    default where not given), for job `job`, named `field` (default: arg) in errors. An argument that is None or
    not a path is left to the function's own checks (no lock)."""
    def wrap(fn):
        signature = inspect.signature(fn)

        @functools.wraps(fn)
        def locked(*args, **kwargs):
            try:
                bound = signature.bind(*args, **kwargs)
            except TypeError:
                return fn(*args, **kwargs)  # the call's own error
            bound.apply_defaults()
            path = bound.arguments.get(arg)
            if not isinstance(path, (str, os.PathLike)) or not os.fspath(path):
                return fn(*args, **kwargs)
            with output_lock(path, job, field=field or arg, folder=folder, beside=beside):
                return fn(*args, **kwargs)

        return locked

    return wrap
