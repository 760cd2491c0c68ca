"""The mark a job leaves in a PNG it writes (a plot, a montage): a tEXt chunk JOB_KEY naming the job, so a later run
tells its own earlier file, which it may replace or remove, from a user's file of the same name, which it may not.
Matplotlib writes the chunk itself (savefig's metadata=); cv2 cannot, so its bytes get it through `marked_png`."""

from __future__ import annotations

import os
import struct
import zlib

JOB_KEY = "envisat job"  # the tEXt keyword; its text is the job, as `envisat JOB` names it ("simulate")
SIGNATURE = b"\x89PNG\r\n\x1a\n"
_HEADER_END = len(SIGNATURE) + 4 + 4 + 13 + 4  # IHDR, always the first chunk: length, type, 13 bytes, CRC


def marked_png(data: bytes, job: str) -> bytes:
    """PNG bytes with the chunk JOB_KEY: job added after the header chunk (where a reader meets it first)."""
    if data[:len(SIGNATURE)] != SIGNATURE or data[12:16] != b"IHDR":
        raise ValueError("expected the bytes of a PNG image")
    body = JOB_KEY.encode("latin-1") + b"\0" + job.encode("latin-1")
    chunk = struct.pack(">I", len(body)) + b"tEXt" + body + struct.pack(">I", zlib.crc32(b"tEXt" + body))
    return data[:_HEADER_END] + chunk + data[_HEADER_END:]


def png_job(path: str) -> str | None:
    """The job the PNG at path names in its JOB_KEY chunk (one that a job wrote), or None: no such file, not a
    PNG, no such chunk before the image data (a user's PNG)."""
    try:
        with open(path, "rb") as fh:
            if fh.read(len(SIGNATURE)) != SIGNATURE:
                return None
            while True:
                head = fh.read(8)
                if len(head) < 8:
                    return None
                length, kind = struct.unpack(">I", head[:4])[0], head[4:]
                if kind in (b"IDAT", b"IEND"):
                    return None
                body = fh.read(length)
                fh.seek(4, os.SEEK_CUR)  # the CRC
                key, _, text = body.partition(b"\0")
                if kind == b"tEXt" and key == JOB_KEY.encode("latin-1"):
                    return text.decode("latin-1")
    except OSError:
        return None


def written_png(path: str, job: str) -> bool:
    """Whether the PNG at path is one `envisat JOB` wrote (its mark names job)."""
    return png_job(path) == job
