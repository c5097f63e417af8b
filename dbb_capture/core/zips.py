"""Reading zips of arrays (``.npz``) whole, every way a damaged one can fail turned into one
:class:`DbbError`.

An ``.npz`` is a zip of ``.npy`` files that numpy reads lazily: a flipped or missing byte shows
up as ``zipfile.BadZipFile``, ``zlib.error``, ``EOFError`` (which click would take for Ctrl-D),
``ValueError`` from a broken ``.npy`` header or ``OSError``, at open or at the first read of an
array. Reading every array at once keeps all of them at the door. Python's zipfile trusts the
central directory alone; :func:`check_zip_headers` also holds each member's local header to it,
because streaming readers (and other tools) read the local headers instead.
"""

from __future__ import annotations

import struct
import zipfile
import zlib
from pathlib import Path

import numpy as np

from .errors import DbbError

# What numpy and zipfile raise on a damaged file (MemoryError: a header claiming a huge array).
DAMAGED = (OSError, ValueError, EOFError, KeyError, TypeError, IndexError, struct.error, zipfile.BadZipFile,
           zlib.error, NotImplementedError, MemoryError, OverflowError, RuntimeError)
ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")     # a zip's first bytes (an empty zip: its end record)
_LOCAL = struct.Struct("<4sHHHHHIIIHH")         # a zip local file header (30 bytes)
_ZIP64_EXTRA = 0x0001
_SIZES_IN_DESCRIPTOR = 0x08                     # flag bit 3: crc and sizes follow the data instead


def read_npz(path: Path, what: str) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` at ``path`` by name (pickled objects refused); ``what`` names
    the file in the one-line error (e.g. ``"PlenOctree"``)."""
    path = Path(path)
    if not path.is_file():
        raise DbbError(f"{what} not found: {path}")
    with open(path, "rb") as f:
        head = f.read(4)
    if head[:4] not in ZIP_MAGIC:
        raise DbbError(f"{what} {path} is not an .npz archive ({'an empty file' if not head else 'not a zip'})")
    try:
        with zipfile.ZipFile(path) as zf:
            check_zip_headers(zf, f"{what} {path}")
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except DbbError:
        raise
    except DAMAGED as e:
        raise DbbError(f"{what} {path} is damaged ({reason(e)})") from None


def check_zip_headers(zf: zipfile.ZipFile, label: str) -> None:
    """Refuse a zip whose members' local headers disagree with its central directory (method,
    flags, time, crc, sizes): a damaged byte there misleads every reader but Python's. ``label``
    names the file in the error (e.g. ``"PlenOctree /a/tree.npz"``)."""
    fp = zf.fp
    for info in zf.infolist():
        fp.seek(info.header_offset)
        raw = fp.read(_LOCAL.size)
        if len(raw) != _LOCAL.size:
            raise DbbError(f"{label} is damaged: the header of {info.filename!r} is cut short")
        sig, _, flags, method, time, date, crc, csize, usize, nlen, xlen = _LOCAL.unpack(raw)
        fp.seek(nlen, 1)            # the name: zipfile compares it when the member is read
        extra = fp.read(xlen)
        sizes = (csize, usize)
        if 0xFFFFFFFF in sizes:
            sizes = _zip64_sizes(extra, sizes)
        ok = (sig == b"PK\x03\x04" and method == info.compress_type and flags == info.flag_bits
              and (time, date) == _dos_time(info.date_time))
        if ok and not flags & _SIZES_IN_DESCRIPTOR:
            ok = crc == info.CRC and sizes == (info.compress_size, info.file_size)
        if not ok:
            raise DbbError(f"{label} is damaged: the local header of {info.filename!r} disagrees with the "
                           "zip's directory")


def _zip64_sizes(extra: bytes, sizes: tuple[int, int]) -> tuple[int, int]:
    """(compressed, uncompressed) sizes from a local header's zip64 extra field where the fixed
    fields hold 0xFFFFFFFF (in the extra field: uncompressed first)."""
    i = 0
    while i + 4 <= len(extra):
        tag, n = struct.unpack_from("<HH", extra, i)
        if tag == _ZIP64_EXTRA:
            body = extra[i + 4:i + 4 + n]
            vals = list(struct.unpack_from(f"<{len(body) // 8}Q", body))
            usize = vals.pop(0) if sizes[1] == 0xFFFFFFFF and vals else sizes[1]
            csize = vals.pop(0) if sizes[0] == 0xFFFFFFFF and vals else sizes[0]
            return csize, usize
        i += 4 + n
    return sizes


def _dos_time(dt: tuple[int, ...]) -> tuple[int, int]:
    """(time, date) MS-DOS fields of a ZipInfo ``date_time``."""
    y, mo, d, h, mi, s = dt
    return h << 11 | mi << 5 | s // 2, (y - 1980) << 9 | mo << 5 | d


def reason(e: BaseException) -> str:
    """An exception as a few words on one line."""
    text = " ".join(str(e).split()) or type(e).__name__
    if text == "File is not a zip file":        # zipfile's words for a missing end record
        return "cut short: the zip's directory at its end is missing"
    return text if len(text) <= 80 else text[:77] + "..."
