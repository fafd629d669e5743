"""What an earlier run of a sweep left in its `out_dir` ([`run_sweep`][]): the chunks it
finished, its automatic chunk size, whether it completed, and its manifest. Files of
another sweep (another fingerprint) make `out_dir` unusable unless the sweep starts over
(`resume=False`, which deletes the sweep files); half-written files of an interrupted run
are deleted. Process 0 decides, and broadcasts its decision to the other processes, so
that every process runs the same chunks (and the same collectives) or raises the same
error."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import warnings

import jax
import numpy as np
from jax.experimental import multihost_utils

from ._sweep_files import (
    _CHUNK_RE,
    _FORMAT,
    _MANIFEST,
    _RESULT,
    _TMP_RE,
    _chunk_bounds,
    _versions,
)


def _mismatch_error(out_dir, differs):
    return (
        f"`run_sweep`: {out_dir!r} holds a different sweep (it differs in: "
        f"{', '.join(differs)}). Pick another `out_dir`, or pass `resume=False` to delete "
        "its sweep files and start over."
    )


@dataclasses.dataclass
class _Scan:
    """What an earlier run left in `out_dir` (`_scan_out_dir`)."""

    chunk_size: int | None = None  # of the earlier run (auto) or the one asked for
    done: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=bool))
    complete: bool = False  # `result.npz` of this sweep is there: nothing to compute
    manifest: dict | None = None


def _scan_out_dir(out_dir, fingerprint, parts, n_points, chunk_size, resume):
    """Find what an earlier run of this sweep finished. Returns `(error, _Scan)`.
    `chunk_size`: None for the automatic size, which is then the earlier run's."""
    scan = _Scan(chunk_size=chunk_size)
    names = os.listdir(out_dir)
    if not resume:
        for name in names:
            if name in (_MANIFEST, _RESULT) or _CHUNK_RE.match(name) or _TMP_RE.match(name):
                os.remove(os.path.join(out_dir, name))
        return None, scan

    for name in names:  # half-written files of an interrupted run
        if _TMP_RE.match(name) and (
            name.startswith((".chunk_", f".{_MANIFEST}.", f".{_RESULT}."))
        ):
            os.remove(os.path.join(out_dir, name))

    path = os.path.join(out_dir, _MANIFEST)
    old = None
    if os.path.exists(path):
        try:
            with open(path) as f:
                old = json.load(f)
        except (OSError, ValueError):
            return (
                f"`run_sweep`: the manifest {path!r} is unreadable. Pick another `out_dir`, "
                "or pass `resume=False` to start over.",
                scan,
            )
        if old.get("format") != _FORMAT:
            return _mismatch_error(out_dir, ["file format"]), scan
        if old.get("fingerprint") != fingerprint:
            old_parts = old.get("fingerprint_parts", {})
            differs = [k for k in parts if old_parts.get(k) != parts[k]] or ["fingerprint"]
            return _mismatch_error(out_dir, differs), scan
        versions = _versions()
        if old.get("versions") != versions:
            warnings.warn(
                f"`run_sweep`: resuming the sweep in {out_dir!r}, started with versions "
                f"{old.get('versions')}; now running with {versions}.",
                stacklevel=4,
            )
        scan.manifest = old
        if scan.chunk_size is None and old.get("chunk_size"):
            scan.chunk_size = int(old["chunk_size"])
        if old.get("complete") and _RESULT in names and scan.chunk_size:
            scan.complete = True
            return None, scan

    found = {}
    for name in sorted(names):
        m = _CHUNK_RE.match(name)
        if not m:
            continue
        i = int(m.group(1))
        try:
            with np.load(os.path.join(out_dir, name), allow_pickle=False) as z:
                fp = str(z["__fingerprint__"])
                ok = int(z["__chunk__"]) == i
                start, stop = int(z["__start__"]), int(z["__stop__"])
                size = int(z["__chunk_size__"]) if "__chunk_size__" in z.files else None
        except Exception as e:  # a damaged file: compute the chunk again
            warnings.warn(
                f"`run_sweep`: ignoring unreadable chunk file {name!r} ({e}); its chunk will "
                "be computed again.",
                stacklevel=4,
            )
            continue
        if fp != fingerprint or not ok:
            return _mismatch_error(out_dir, [f"chunk file {name}"]), scan
        if scan.chunk_size is None:  # automatic size and no manifest: the files' size
            scan.chunk_size = size
        found[i] = (name, start, stop)
    if scan.chunk_size is None:
        return None, scan
    n_chunks = math.ceil(n_points / scan.chunk_size)
    scan.done = np.zeros(n_chunks, dtype=bool)
    for i, (name, start, stop) in found.items():
        expected = _chunk_bounds(i, scan.chunk_size, n_points)
        if i >= n_chunks or (start, stop) != expected:
            return _mismatch_error(out_dir, [f"chunk file {name}"]), scan
        scan.done[i] = True
    return None, scan


def _resume_scan(spec, resume) -> _Scan:
    """What to resume of the sweep `spec` (a `_SweepSpec`), decided on process 0 and
    broadcast (`_scan_out_dir`). Raises on every process if process 0 refuses `out_dir`."""
    out_dir, auto = spec.out_dir, spec.auto
    n_points, is_writer = spec.n_points, spec.is_writer
    error = scan_error = None
    scan = _Scan(chunk_size=None if auto else spec.chunk_size)
    if is_writer:
        try:
            os.makedirs(out_dir, exist_ok=True)
            error, scan = _scan_out_dir(
                out_dir, spec.fingerprint, spec.parts, n_points, scan.chunk_size, resume
            )
        except Exception as e:  # raised below, after the other processes have been told
            scan_error = e
            error = f"Cannot use {out_dir!r}: {e!r}"
    if jax.process_count() > 1:
        head = np.array([error is not None, scan.complete, scan.chunk_size or 0], np.int64)
        head = np.asarray(multihost_utils.broadcast_one_to_all(head))
        if not is_writer and head[0]:
            error = f"Process 0 refused to resume the sweep in {out_dir!r}; see its error."
        scan.complete, scan.chunk_size = bool(head[1]), int(head[2]) or None
        n_known = math.ceil(n_points / scan.chunk_size) if scan.chunk_size else 0
        done = np.zeros(n_known, dtype=np.int32)
        done[: len(scan.done)] = scan.done[:n_known]
        if n_known:
            done = np.asarray(multihost_utils.broadcast_one_to_all(done))
        scan.done = done.astype(bool)
    if scan_error is not None:
        raise scan_error
    if error is not None:
        raise ValueError(error)
    return scan
