"""Files written by the library and its commands: the one atomic write (a temporary file
in the same folder, then `os.replace`, so a reader never sees half a file and an
interrupted run leaves the old file), the one `.npz` writer and the one JSON sanitiser
(JSON has no NaN and no NumPy types)."""

from __future__ import annotations

import contextlib
import json
import math
import os
import uuid
import zipfile
from collections.abc import Callable
from typing import IO

import numpy as np


def atomic_write(path, data: bytes | str | Callable[[IO[bytes]], None], *,
                 durable: bool = False) -> None:
    """Write `path` (str or `Path`) through a hidden temporary file in the same folder and
    `os.replace`. `data`: the bytes (a `str` is encoded as UTF-8), or a function that
    writes into the open binary file. `durable`: flush the file and the rename to the
    disk (`fsync`) as well, for checkpoints that must survive a power cut. Every process
    uses its own temporary name, so processes (`jax.distributed`) that write the same
    deterministic file do not collide: the last complete write wins."""
    path = os.fspath(path)
    d, base = os.path.split(path)
    # Not `tempfile.mkstemp`: its files are private (0600); this one obeys the umask.
    tmp = os.path.join(d, f".{base}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            if callable(data):
                data(f)
            else:
                f.write(data.encode("utf-8") if isinstance(data, str) else data)
            f.flush()
            if durable:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise
    if durable:
        fsync_dir(d)


#: Arrays from this size (bytes) on are written from their own memory (`save_npz`).
_NPZ_DIRECT_BYTES = 1 << 16


def save_npz(file, arrays: dict, *, zip_file: zipfile.ZipFile | None = None) -> None:
    """Write `arrays` (name -> array) as `np.savez` does: an uncompressed zip of `.npy`
    members that `np.load` reads (no pickled objects). `file`: a path or an open binary
    file; or `zip_file`, an open `zipfile.ZipFile` to add the members to (`file` None).

    `np.savez` copies every array in pieces of up to 16 MiB before writing them, and in a
    fresh process every piece is new memory the system must map (a 4 M-point map's 76 MB
    cost it 0.03-0.05 s more than the write). Here a C-contiguous array of at least
    `_NPZ_DIRECT_BYTES` is written from its own memory; smaller ones, and those of other
    layouts, as `np.savez` writes them."""
    if zip_file is None:
        with zipfile.ZipFile(file, mode="w", compression=zipfile.ZIP_STORED,
                             allowZip64=True) as zf:
            save_npz(None, arrays, zip_file=zf)
        return
    for name, a in arrays.items():
        a = np.asanyarray(a)
        if a.dtype.hasobject:
            raise ValueError(f"`save_npz`: {name!r} holds Python objects ({a.dtype}); "
                             "the files hold plain arrays only.")
        with zip_file.open(f"{name}.npy", "w", force_zip64=True) as f:
            if (a.nbytes >= _NPZ_DIRECT_BYTES and a.flags.c_contiguous and a.ndim
                    and a.dtype.names is None):  # a short header: format 1.0
                np.lib.format.write_array_header_1_0(
                    f, np.lib.format.header_data_from_array_1_0(a))
                f.write(memoryview(a.reshape(-1).view(np.uint8)))
            else:
                np.lib.format.write_array(f, a, allow_pickle=False)


def fsync_dir(folder: str) -> None:
    """Make a rename in `folder` durable (POSIX; a no-op where folders cannot be opened)."""
    with contextlib.suppress(OSError, AttributeError):
        dfd = os.open(folder or ".", os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


def json_safe(obj):
    """`obj` as plain JSON values: mappings with string keys, lists, numbers, strings,
    booleans and None. NumPy and JAX scalars and arrays (anything with `__array__`)
    become numbers and (nested) lists; non-finite floats become None (JSON has no NaN or
    infinity)."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    if isinstance(obj, bool | int | str) or obj is None:
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, np.generic | np.ndarray) or hasattr(obj, "__array__"):
        a = np.asarray(obj)
        if a.dtype.kind in "fc":
            return json_safe(a.tolist())
        return a.tolist()
    return obj


def json_text(obj, *, indent: int | None = 2) -> str:
    """`obj` as strict JSON text (`json_safe` first: non-finite numbers become null)."""
    return json.dumps(json_safe(obj), indent=indent, allow_nan=False)


def write_json(path, obj, *, indent: int | None = 2) -> None:
    """Write `obj` to `path` as strict JSON (`json_text`), atomically (`atomic_write`)."""
    atomic_write(path, json_text(obj, indent=indent) + "\n")
