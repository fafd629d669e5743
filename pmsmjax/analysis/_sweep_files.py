"""The files of a sweep in its `out_dir` ([`run_sweep`][]). Each is written atomically (to
a hidden temporary file in the same folder, then `os.replace`); the chunk files and
`result.npz` are flushed to the disk (`save_npz`: uncompressed, as `np.savez` writes):

- `chunk_000000.npz`, `chunk_000001.npz`, ...: the outputs of the points of one chunk
  (padding removed), plus `__fingerprint__`, `__metadata__` (the user metadata as JSON),
  `__chunk__`, the point range `__start__` to `__stop__` (exclusive) and `__chunk_size__`.
  They are the source of truth while a sweep runs. The last chunk gets no file of its own
  (`result.npz`, written at once, holds it), and once `result.npz` is written the chunk
  files are deleted, unless they are kept (`keep_chunks`, by default when `chunk_size` is
  given): what stays is what resuming needs, never the result twice.
- `sweep.json`: the manifest. Fingerprint of the sweep and its parts (grid, chunk size or
  `"auto"`, output structure, user metadata, and a hash of `fn`'s jaxpr), the user
  metadata, package versions, devices, the chunk and block sizes, and for every chunk its
  status, wall time, points per second and the number of points with non-finite outputs
  or a non-zero `status`. Rewritten at most every `_MANIFEST_INTERVAL_S` while chunks
  finish, and at the end.
- `result.npz`: when the sweep is complete, every output (in point order, reshaped to the
  grid shape if the grid came from `grid_product`) and the grid itself as `grid/<key>`.
  Running a complete sweep again reads it and computes nothing.


Hidden `.*.tmp` files are half-written files of an interrupted run; they are ignored and
deleted when the sweep resumes (`pmsmjax.analysis._sweep_resume`). Run one sweep per
`out_dir` at a time.
"""

from __future__ import annotations

import contextlib
import datetime
import importlib.metadata
import json
import math
import os
import platform
import re
import uuid
import zipfile

import jax
import numpy as np

from .._files import atomic_write, fsync_dir, save_npz


_FORMAT = "pmsmjax-sweep/1"
_MANIFEST = "sweep.json"
_RESULT = "result.npz"
_CHUNK_RE = re.compile(r"^chunk_(\d{6,})\.npz$")
_TMP_RE = re.compile(r"^\..+\.tmp$")


def _chunk_name(i: int) -> str:
    return f"chunk_{i:06d}.npz"


def _chunk_bounds(i, chunk_size, n_points) -> tuple[int, int]:
    """The points `start <= p < stop` of chunk `i` of `chunk_size` points."""
    i, c = int(i), int(chunk_size)
    return i * c, min((i + 1) * c, n_points)


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _versions():
    versions = {"python": platform.python_version()}
    for pkg in ("pmsmjax", "jax", "jaxlib", "numpy"):
        try:
            versions[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:  # pragma: no cover
            versions[pkg] = None
    return versions


# --------------------------------------------------------------------------------------
# Chunk files


def _write_chunk(out_dir, i, arrays, fingerprint, metadata_json, start, stop, chunk_size):
    meta = {
        "__chunk_size__": np.array(chunk_size),
        "__fingerprint__": np.array(fingerprint),
        "__metadata__": np.array(metadata_json),
        "__chunk__": np.array(i),
        "__start__": np.array(start),
        "__stop__": np.array(stop),
    }
    atomic_write(os.path.join(out_dir, _chunk_name(i)),
                 lambda f: save_npz(f, {**arrays, **meta}), durable=True)


def _load_outputs(path, out_names, fingerprint, what: str) -> dict[str, np.ndarray]:
    """The outputs `out_names` of a finished file of this sweep (`what` names it in the
    error when another host cannot read it)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["__fingerprint__"]) != fingerprint:
                raise ValueError(f"{path!r} belongs to another sweep.")
            return {n: z[n] for n in out_names}
    except FileNotFoundError:
        raise FileNotFoundError(
            f"`run_sweep`: {what} {path!r} is not readable from process "
            f"{jax.process_index()}. With several hosts, `out_dir` must be on a shared file "
            "system to resume."
        ) from None


def _load_chunk(path, out_names, fingerprint) -> dict[str, np.ndarray]:
    return _load_outputs(path, out_names, fingerprint, "finished chunk")


def _load_result(path, out_names, fingerprint) -> dict[str, np.ndarray]:
    return _load_outputs(path, out_names, fingerprint, "the finished sweep's")


# --------------------------------------------------------------------------------------
# The manifest


def _new_manifest(spec, chunk_size, old):
    """The manifest of the sweep `spec` (a `_SweepSpec`) with no chunk done yet;
    `chunk_size`: None while the automatic size is not chosen; `old`: the manifest of an
    earlier run of it, or None."""
    devices = spec.mesh.devices.reshape(-1)
    n_points = spec.n_points
    n_chunks = None if chunk_size is None else math.ceil(n_points / chunk_size)
    return {
        "format": _FORMAT,
        "fingerprint": spec.fingerprint,
        "fingerprint_parts": spec.parts,
        "metadata": json.loads(spec.metadata_json),
        "n_points": n_points,
        "chunk_size": chunk_size,
        "n_chunks": n_chunks,
        "grid": {k: str(v.dtype) for k, v in spec.host_grid.items()},
        "grid_shape": list(spec.shape) if spec.shape is not None else None,
        "outputs": {
            n: {"dtype": str(s.dtype), "shape": list(s.shape)}
            for n, s in zip(spec.out_names, spec.out_specs)
        },
        "versions": _versions(),
        "devices": {
            "count": int(devices.size),
            "platform": devices[0].platform,
            "kind": devices[0].device_kind,
            "process_count": jax.process_count(),
        },
        "created": (old or {}).get("created", _now()),
        "updated": _now(),
        "compile_seconds": (old or {}).get("compile_seconds"),
        "complete": False,
        "n_nonfinite": None,
        "n_failed": None,
        "chunks": {},
    }


def _record(manifest, info, extra, file):
    """Enter the finished chunk `info` (a `ChunkInfo`) in the manifest, with its `file`
    (None: none of its own) and the timings `extra`."""
    manifest["chunks"][str(info.index)] = {
        "status": "done",
        "file": file,
        "start": info.start,
        "stop": info.stop,
        "n_nonfinite": info.n_nonfinite,
        "n_failed": info.n_failed,
        **extra,
    }


def _write_manifest(out_dir, manifest):
    manifest["chunks"] = dict(sorted(manifest["chunks"].items(), key=lambda kv: int(kv[0])))
    text = json.dumps(manifest, indent=1, allow_nan=False)
    # Not flushed to the disk (`fsync`): while a sweep runs the chunk files, which are,
    # are the source of truth.
    atomic_write(os.path.join(out_dir, _MANIFEST), text)


# --------------------------------------------------------------------------------------
# The result


def _grid_arrays(host_grid, shape) -> dict[str, np.ndarray]:
    return {f"grid/{k}": v if shape is None else v.reshape(shape) for k, v in host_grid.items()}


class _ResultFile:
    """`result.npz` (uncompressed `.npy` members of a zip file, as `np.savez` writes it;
    by `save_npz`), written in parts to a hidden temporary file that is renamed when
    complete."""

    def __init__(self, out_dir):
        self.path = os.path.join(out_dir, _RESULT)
        d, base = os.path.split(self.path)
        self.tmp = os.path.join(d, f".{base}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
        self.file = self.zip = self.started = None
        self.done = False

    def begin(self, writer, arrays):
        """Open the file and write `arrays` (the grid) in the writer thread."""
        fd = os.open(self.tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0),
                     0o666)
        self.file = os.fdopen(fd, "wb")
        self.zip = zipfile.ZipFile(self.file, mode="w", compression=zipfile.ZIP_STORED,
                                   allowZip64=True)
        self.started = writer.submit(self.write, arrays)

    def write(self, arrays):
        save_npz(None, arrays, zip_file=self.zip)

    def commit(self, arrays, *, durable):
        """Write the rest, close, flush to the disk if `durable`, and rename."""
        self.started.result()
        self.write(arrays)
        self.zip.close()
        self.file.flush()
        if durable:
            os.fsync(self.file.fileno())
        self.file.close()
        os.replace(self.tmp, self.path)
        self.done = True
        if durable:
            fsync_dir(os.path.dirname(self.path))  # the rename

    def abort(self):
        if self.done or self.file is None:
            return
        with contextlib.suppress(Exception):
            self.started.result()
        with contextlib.suppress(Exception):
            self.zip.close()
        with contextlib.suppress(Exception):
            self.file.close()
        with contextlib.suppress(OSError):
            os.remove(self.tmp)
        self.file = None


def _complete(spec, results, result_file, manifest):
    """Write `result.npz` (unless `spec.keep_result` is False) and the complete manifest
    (process 0), then delete the chunk files unless they are kept: the result holds all
    of them. `result.npz` is flushed to
    the disk (`fsync`) when it replaces chunk files; when no chunk file was written (one
    chunk), it is written like the command's other outputs."""
    manifest["complete"] = True
    if not spec.is_writer:
        return
    out_dir, shape, keep_chunks = spec.out_dir, spec.shape, spec.keep_chunks
    arrays = dict(zip(spec.out_names, results))
    if shape is not None:
        arrays = {k: v.reshape(*shape, *v.shape[1:]) for k, v in arrays.items()}
    chunk_files = [name for name in os.listdir(out_dir) if _CHUNK_RE.match(name)]
    if spec.keep_result:
        result_file.commit({**arrays, "__fingerprint__": np.array(spec.fingerprint)},
                           durable=bool(chunk_files) and not keep_chunks)
    manifest["result"] = _RESULT if spec.keep_result else None
    manifest["n_nonfinite"] = sum(c["n_nonfinite"] for c in manifest["chunks"].values())
    failed = [c["n_failed"] for c in manifest["chunks"].values()]
    manifest["n_failed"] = None if not spec.status_leaves else sum(failed)
    if not keep_chunks:
        for c in manifest["chunks"].values():
            c["file"] = None
    manifest["updated"] = _now()
    _write_manifest(out_dir, manifest)
    if not keep_chunks:
        for name in chunk_files:
            with contextlib.suppress(FileNotFoundError):
                os.remove(os.path.join(out_dir, name))
