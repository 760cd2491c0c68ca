"""Atomic file writing: a temp file in the destination's folder, then os.replace, so a killed job never
leaves a partial output under the final name."""

from __future__ import annotations

import contextlib
import os
import tempfile
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only: numpy is imported where it is used
    import numpy as np


def usual_mode(folder: bool = False) -> int:
    """The mode a new file (0o666) or folder (0o777) gets under the process's umask: what an output made through a
    temporary (mkstemp's 0600, mkdtemp's 0700) is given before it takes its name."""
    umask = os.umask(0)
    os.umask(umask)
    return (0o777 if folder else 0o666) & ~umask


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's process
    return True


def partial_owner_alive(name: str) -> bool:
    """Whether a partial file or folder named `name` (.tmp-PID-..., .tmp-WORD-PID-...: atomic_path's,
    staged_folder's, an export's stage) belongs to a process still running: another job writing the same folder
    now, whose files are not to be removed under it."""
    parts = name.removeprefix(".tmp-").split("-", 2)
    pid = parts[0] if parts[0].isdigit() else parts[1] if len(parts) > 1 else ""
    return pid.isdigit() and int(pid) != os.getpid() and _alive(int(pid))


def _partial_prefix(path: str, pid: int | str) -> str:
    """The name's start of atomic_path's temporary file for `path` in process `pid`: '.tmp-PID-NAME-'."""
    return f".tmp-{pid}-{os.path.basename(path)[:100]}-"


def sweep_stale_partials(path: str) -> list[str]:
    """Remove the temporary files of `path` that a writer killed mid-write left beside it (SIGKILL: no clean-up
    ran): those named by _partial_prefix whose process is gone; a running writer's, and any other name, stay.
    Returns the names removed."""
    folder, gone = os.path.dirname(os.path.abspath(path)), []
    name_start = _partial_prefix(path, "").removeprefix(".tmp--")  # 'NAME-'
    with contextlib.suppress(FileNotFoundError, NotADirectoryError):
        for name in os.listdir(folder):
            if not name.startswith(".tmp-"):
                continue
            pid, _, rest = name.removeprefix(".tmp-").partition("-")
            if pid.isdigit() and rest.startswith(name_start) and not _alive(int(pid)) and \
                    os.path.isfile(os.path.join(folder, name)):
                with contextlib.suppress(FileNotFoundError):
                    os.remove(os.path.join(folder, name))
                gone.append(name)
    return gone


@contextlib.contextmanager
def atomic_path(path: str, suffix: str = ""):
    """Yield a temporary path next to `path`; on success it is renamed to `path`, on error removed. A killed
    earlier writer's temporary file of the same path goes first (sweep_stale_partials)."""
    folder = os.path.dirname(os.path.abspath(path))
    sweep_stale_partials(path)
    fd, tmp = tempfile.mkstemp(prefix=_partial_prefix(path, os.getpid()), suffix=suffix or os.path.splitext(path)[1],
                               dir=folder)
    os.close(fd)
    mode = usual_mode()
    os.chmod(tmp, mode)  # mkstemp makes 0600 files; outputs get the user's usual mode
    try:
        yield tmp
        os.chmod(tmp, mode)  # again: a writer may have replaced the file (safetensors' save_file makes it 0600)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


NO_ROOM_PROBE_BYTES = 16 << 20  # what no_room_error writes to learn why a writer thread stopped


def no_room_error(path: str, err: BaseException) -> BaseException:
    """The error to raise for a writer that failed outside Python (Rerun's file-writer thread: a RuntimeError
    'File-writer thread shut down prematurely', the OS's reason only logged) while writing `path`: an OSError
    naming path where the folder takes no more bytes (a write of NO_ROOM_PROBE_BYTES beside it is refused with
    ENOSPC, EDQUOT or EFBIG: a full disk, a quota, `ulimit -f`), else err itself. The probe's file is removed."""
    import errno

    fd, probe = tempfile.mkstemp(prefix=_partial_prefix(path, os.getpid()), dir=os.path.dirname(os.path.abspath(path)))
    try:
        block = bytes(1 << 20)
        for _ in range(NO_ROOM_PROBE_BYTES // len(block)):
            os.write(fd, block)
    except OSError as refused:
        if refused.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
            return OSError(refused.errno, os.strerror(refused.errno), path)
    finally:
        os.close(fd)
        os.remove(probe)
    return err


STAGE_PREFIX = ".tmp-stage-"  # staged_folder's folder inside the destination (what a killed job leaves behind)


def stage_prefix(prefix: str = STAGE_PREFIX) -> str:
    """The name's start of a staging folder this process makes: prefix, its pid and '-' (so a later job knows a
    killed job's folder: sweep_stale_stages)."""
    return f"{prefix}{os.getpid()}-"


def sweep_stale_stages(out_dir: str, prefix: str = STAGE_PREFIX) -> list[str]:
    """Remove the staging folders in out_dir that a job killed mid-write left (SIGKILL, a power cut: no clean-up
    ran): those named by stage_prefix(prefix) whose process is gone; a running job's, and any other name, stay.
    Returns the names removed."""
    import shutil

    gone = []
    with contextlib.suppress(FileNotFoundError, NotADirectoryError):
        for name in os.listdir(out_dir):
            pid = name.removeprefix(prefix).split("-", 1)[0]
            if name.startswith(prefix) and pid.isdigit() and not _alive(int(pid)) and \
                    os.path.isdir(os.path.join(out_dir, name)):
                shutil.rmtree(os.path.join(out_dir, name), ignore_errors=True)
                gone.append(name)
    return gone


@contextlib.contextmanager
def staged_folder(out_dir: str, outputs=()):
    """Yield a fresh hidden folder inside out_dir (created, parents too) for a job's outputs. When the block
    completes, every file in it is moved into out_dir (os.replace: each file whole), the files named in
    `outputs` that this job did not write (an earlier run's, now stale) are removed from out_dir, and the
    folder goes. A killed job's staging folder found there is removed first (sweep_stale_stages). On an error or an interrupt the folder and its partial files are removed and out_dir is left
    as it was (an earlier run's outputs intact)."""
    import shutil

    os.makedirs(out_dir, exist_ok=True)
    sweep_stale_stages(out_dir)
    stage = tempfile.mkdtemp(prefix=stage_prefix(), dir=out_dir)
    try:
        yield stage
        written = set(os.listdir(stage))
        for name in outputs:
            if name not in written and os.path.isfile(os.path.join(out_dir, name)):
                os.remove(os.path.join(out_dir, name))
        for name in sorted(written):
            os.replace(os.path.join(stage, name), os.path.join(out_dir, name))
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def atomic_write_text(path: str, text: str) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)


def save_npz(path: str, arrays: dict) -> None:
    """Write arrays to an .npz atomically and byte-reproducibly (fixed zip timestamps, sorted keys).

    numpy.savez stamps every member with the current time, so the same data would give different bytes. A
    value may be a StreamedArray: its chunks are written one after the other, so an array larger than memory is
    never held whole; the file's bytes are those of the same array given whole.
    """
    import zipfile

    import numpy as np

    with atomic_path(path, suffix=".npz") as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
            for key in sorted(arrays):
                info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.external_attr = 0o644 << 16
                with zf.open(info, "w", force_zip64=True) as fh:
                    if isinstance(arrays[key], StreamedArray):
                        arrays[key].write_npy(fh)
                    else:
                        np.lib.format.write_array(fh, np.asanyarray(arrays[key]), allow_pickle=False)


class NotAnNpz(ValueError):
    """A file given as an .npz that is not a zip archive (an .npy, a text file, anything else)."""


@contextlib.contextmanager
def open_npz(path: str):
    """The .npz at path, its arrays read without pickles (numpy's NpzFile), through a file closed on every way
    out: numpy's np.load keeps its own file open where the zip is damaged. NotAnNpz where the file does not start
    as a zip archive (numpy would read an .npy as one array, or try a pickle); numpy's and zipfile's errors as
    they raise them otherwise."""
    import numpy as np

    with open(path, "rb") as fh:
        if fh.read(4) != b"PK\x03\x04":
            raise NotAnNpz(f"{path}: not an .npz file (not a zip archive)")
        fh.seek(0)
        with np.load(fh, allow_pickle=False) as z:
            yield z


class StreamedArray:
    """An array given as its shape, dtype and chunks (a callable returning an iterable of arrays whose rows,
    concatenated in C order, make the array), for save_npz."""

    def __init__(self, shape: tuple, dtype, chunks):
        import numpy as np

        self.shape, self.dtype, self.chunks = tuple(int(n) for n in shape), np.dtype(dtype), chunks

    def write_npy(self, fh) -> None:
        """The .npy bytes (header as numpy.lib.format.write_array writes it, then the data) to a writable file."""
        import numpy as np

        write_npy_header(fh, self.shape, self.dtype)
        want = int(np.prod(self.shape, dtype=np.int64))
        n = 0
        for chunk in self.chunks():
            chunk = np.ascontiguousarray(chunk, dtype=self.dtype)
            fh.write(chunk.tobytes())
            n += chunk.size
        if n != want:
            raise ValueError(f"streamed array of shape {self.shape}: its chunks held {n} values, expected {want}")


def write_npy_header(fh, shape: tuple, dtype) -> None:
    """An .npy header for a C-ordered array (format 1.0, as numpy.lib.format.write_array picks for it)."""
    import numpy as np

    fmt = np.lib.format
    header = {"descr": fmt.dtype_to_descr(np.dtype(dtype)), "fortran_order": False, "shape": tuple(shape)}
    fmt.write_array_header_1_0(fh, header)


class NpyRowWriter:
    """An .npy file of shape (n_rows, *row_shape) written rows at a time (appended in order), so a long run's
    per-frame array is never held whole. close() checks that every row was written."""

    def __init__(self, path: str, n_rows: int, row_shape: tuple, dtype):
        import numpy as np

        self.path, self.n_rows, self.row_shape, self.dtype = path, int(n_rows), tuple(row_shape), np.dtype(dtype)
        self.written = 0
        self.fh = open(path, "wb")
        write_npy_header(self.fh, (self.n_rows,) + self.row_shape, self.dtype)

    def write(self, rows) -> None:
        import numpy as np

        rows = np.ascontiguousarray(rows, dtype=self.dtype)
        if rows.shape[1:] != self.row_shape or self.written + len(rows) > self.n_rows:
            raise ValueError(f"{self.path}: rows of shape {rows.shape} after {self.written} of {self.n_rows} rows "
                             f"of shape {self.row_shape}")
        self.fh.write(rows.tobytes())
        self.written += len(rows)

    def close(self) -> None:
        self.fh.close()
        if self.written != self.n_rows:
            raise ValueError(f"{self.path}: {self.written} of {self.n_rows} rows written")


def npy_info(path: str) -> tuple[tuple, "np.dtype", int]:
    """(shape, dtype, data offset in bytes) of a C-ordered .npy file, from its header."""
    import numpy as np

    fmt = np.lib.format
    with open(path, "rb") as fh:
        version = fmt.read_magic(fh)
        read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape, fortran, dtype = read(fh)
        if fortran:
            raise ValueError(f"{path}: a Fortran-ordered array, expected C order")
        return shape, dtype, fh.tell()


def read_npy_rows(path: str, start: int, stop: int):
    """Rows [start, stop) of a C-ordered .npy file, read from the file (no memory map: the rows read are the only
    ones the process holds)."""
    import numpy as np

    shape, dtype, offset = npy_info(path)
    start, stop = max(0, int(start)), min(int(stop), shape[0])
    row = int(np.prod(shape[1:], dtype=np.int64))
    n = max(stop - start, 0)
    with open(path, "rb") as fh:
        fh.seek(offset + start * row * dtype.itemsize)
        data = np.fromfile(fh, dtype=dtype, count=n * row)
    if data.size != n * row:
        raise ValueError(f"{path}: truncated (rows {start}..{stop} of {shape[0]})")
    return data.reshape((n,) + tuple(shape[1:]))


def sha256_file(path: str) -> str:
    """Hex sha256 of a file, read in 1 MiB blocks (how resumable jobs check what an earlier run wrote)."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def json_safe(x):
    """Plain data for strict JSON: NaN and infinities become null (in dicts, lists and tuples, recursively)."""
    import math

    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
