"""Chunked, sharded and resumable runner for large parameter sweeps.

`run_sweep(fn, grid, ...)` evaluates a per-point function `fn` on every point of a grid.
The points are evaluated in blocks of one fixed length by one compiled `jit(vmap(fn))`,
each block sharded across all devices of a `jax.sharding.Mesh` (by default every device
in `jax.devices()`, which under `jax.distributed` includes the devices of every host).
Blocks are grouped into chunks, the unit of resuming: every finished chunk is written to
disk at once, so an interrupted sweep resumes where it stopped.

Chunk size. Given (`chunk_size=N`), a chunk is one block of N points (padded to a multiple
of the device count). By default (`chunk_size=None`) the runner times the first block (at
most `_AUTO_BLOCK_PER_DEVICE` points per device) and makes a chunk as many blocks as last
about `_AUTO_CHUNK_SECONDS`, with at most `_AUTO_CHUNK_BYTES` of outputs, the points shared
evenly between the chunks; the size is kept in the manifest and the chunk files, and a
resumed sweep uses it again. The block length does not depend on the grouping, so the
results are the same bit for bit however the blocks fall into chunks.

Overlap. Blocks are dispatched asynchronously, two at a time: the next block runs while a
finished one is copied to the host, and a finished chunk is written by a writer thread
while the devices compute the next one. A chunk is final (`on_chunk_done`) once its file
is written; the next chunk's file is only written after that.

Files in `out_dir` (all written atomically: to a temporary file, then `os.replace`; the
chunk files and `result.npz` are flushed to the disk, `np.savez`, uncompressed):

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
deleted when the sweep resumes. Run one sweep per `out_dir` at a time.

**Several hosts.** Start the same script on every host and call
`jax.distributed.initialize()` before any other JAX call (on SLURM or Cloud TPU it finds
the coordinator itself; otherwise pass `coordinator_address="host0:1234"`,
`num_processes=P` and `process_id=p`). Every process must build the same grid. Each process
places the slices of every chunk that belong to its own devices
(`jax.make_array_from_callback`), the chunk runs SPMD over all devices, and the outputs are
gathered on every process (`multihost_utils.process_allgather`). Only process 0 writes
files and shows the progress bar; its decisions on resuming and its automatic chunk size
are broadcast to the others.
Every process returns the full result; chunks finished by an earlier run are read from
`out_dir`, which must then be on a file system that all hosts see.
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import dataclasses
import datetime
import hashlib
import importlib.metadata
import json
import math
import os
import platform
import re
import time
import uuid
import warnings
import zipfile
from collections.abc import Callable, Mapping
from typing import Any, NoReturn

import jax
import jax.extend
import jax.tree_util as jtu
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec


_FORMAT = "pmsmjax-sweep/1"
_MANIFEST = "sweep.json"
_RESULT = "result.npz"
_CHUNK_RE = re.compile(r"^chunk_(\d{6,})\.npz$")
_TMP_RE = re.compile(r"^\..+\.tmp$")
# How often the manifest is rewritten while chunks finish. The chunk files are the source of
# truth, so a manifest that lags behind loses nothing; this only bounds the cost of
# rewriting a large manifest after every small chunk.
_MANIFEST_INTERVAL_S = 2.0
# The automatic chunk size (`chunk_size=None`): a chunk lasts about this long (s) at the
# rate measured on the first block, and holds at most this many bytes of outputs.
_AUTO_CHUNK_SECONDS = 4.0
_AUTO_CHUNK_BYTES = 512 * 2**20
# ... in blocks of at most this many points per device (one compiled evaluation).
_AUTO_BLOCK_PER_DEVICE = 2**16
# Blocks on the devices at a time (asynchronous dispatch): the next block runs while the
# last one is copied and its chunk counted and handed to the writer thread.
_DEPTH = 2
_DONE: concurrent.futures.Future = concurrent.futures.Future()
_DONE.set_result(None)


class SweepGrid(dict):
    """A flattened Cartesian-product grid, made by [`grid_product`][].

    A plain `dict` mapping each axis name to a 1-D array of length
    `N = prod(shape)` (first axis slowest, like `np.meshgrid(..., indexing="ij")` flattened
    in C order), which also remembers:

    - `shape`: the grid shape, `tuple(len(a) for a in axes.values())`;
    - `axes`: the 1-D axis arrays it was built from.

    [`run_sweep`][] reshapes its outputs from `(N, ...)` to `(*shape, ...)` for such grids.

    !!! note
        JAX treats a `dict` subclass as a single leaf, not as a PyTree. Pass `dict(grid)`
        to JAX transformations (this drops `shape`).
    """

    shape: tuple[int, ...]
    axes: dict[str, np.ndarray]

    def __init__(self, points, *, shape, axes):
        super().__init__(points)
        self.shape = tuple(int(s) for s in shape)
        self.axes = dict(axes)

    def __repr__(self):
        axes = ", ".join(f"{k}: {len(v)}" for k, v in self.axes.items())
        return f"SweepGrid(shape={self.shape}, axes={{{axes}}})"


def grid_product(**axes) -> SweepGrid:
    """Cartesian product of 1-D axes, flattened into a grid for [`run_sweep`][].

    **Arguments:**

    - `**axes`: each keyword names one grid axis and gives its values as a non-empty 1-D
      array (or sequence).

    **Returns:**

    A [`SweepGrid`][]: a `dict` of 1-D NumPy arrays of length `prod(len(a))`, in the order
    of `np.meshgrid(*axes.values(), indexing="ij")` flattened in C order (the first axis
    varies slowest), with `.shape` and `.axes` set.

    ```python
    grid = grid_product(R_s=np.linspace(0.5, 1.0, 3), w_m=np.linspace(100.0, 300.0, 5))
    grid.shape        # (3, 5)
    grid["w_m"][:6]   # 100, 150, 200, 250, 300, 100
    ```
    """
    if not axes:
        raise ValueError("`grid_product()` needs at least one axis, e.g. `grid_product(x=xs)`.")
    arrays = {}
    for name, values in axes.items():
        a = _as_numeric(f"grid_product({name}=...)", values)
        if a.ndim != 1:
            raise ValueError(
                f"`grid_product({name}=...)` must be a 1-D array; got shape {a.shape}."
            )
        if a.size == 0:
            raise ValueError(f"`grid_product({name}=...)` is empty; every axis needs a value.")
        arrays[name] = a
    mesh = np.meshgrid(*arrays.values(), indexing="ij")
    points = {name: m.reshape(-1) for name, m in zip(arrays, mesh)}
    return SweepGrid(points, shape=tuple(a.size for a in arrays.values()), axes=arrays)


@dataclasses.dataclass(frozen=True)
class ChunkInfo:
    """What [`run_sweep`][] passes to `on_chunk_done` after each chunk is final.

    - `index`: chunk number, from 0.
    - `start`, `stop`: the chunk covers grid points `start <= i < stop`.
    - `loaded`: True if the chunk was read from an earlier run's file, False if computed now.
    - `seconds`: wall time of the chunk (s); `None` when loaded.
    - `n_nonfinite`: points of the chunk with a NaN or inf in any output.
    - `n_failed`: points with a non-zero `status` output; `None` if `fn` returns no status.
    - `input_sharding`, `output_sharding`: the actual shardings of the chunk's device input
      and output arrays (one leaf each); `None` when loaded.
    """

    index: int
    start: int
    stop: int
    loaded: bool
    seconds: float | None
    n_nonfinite: int
    n_failed: int | None
    input_sharding: jax.sharding.Sharding | None = None
    output_sharding: jax.sharding.Sharding | None = None


def run_sweep(
    fn: Callable[[dict[str, Any]], Any],
    grid: Mapping[str, Any],
    *,
    out_dir: str | os.PathLike,
    chunk_size: int | None = None,
    batch_size: int | None = None,
    metadata: Mapping[str, Any] | None = None,
    progress: bool = True,
    resume: bool = True,
    mesh: Mesh | None = None,
    dtype: Any = None,
    allow_nonfinite: bool = False,
    on_chunk_done: Callable[[ChunkInfo], None] | None = None,
    keep_chunks: bool | None = None,
) -> Any:
    """Evaluate `fn` on every point of `grid`, in chunks sharded over all devices.

    **Arguments:**

    - `fn`: a pure function of one point, `fn(point) -> outputs`. `point` is a `dict` with
      the keys of `grid` and scalar (0-d) array values; `outputs` is any PyTree of arrays
      (a `dict`, or e.g. a `pmsmjax.Trajectory`). It is vmapped and compiled once. A
      failing point must not raise: return NaNs, and/or an integer `status` output (0 =
      success; any integer leaf whose PyTree path has a part named `status`, such as the
      `.status` of `pmsmjax.simulate(..., throw=False)`). Points with non-finite outputs
      and with a non-zero status are counted per chunk in the manifest. Output names in
      the files are the PyTree paths joined by `/` (`"eig"`, `"status/_value"`).
    - `grid`: a `dict` of 1-D arrays of equal length `N`, one entry per input of `fn`, or a
      [`SweepGrid`][] from [`grid_product`][]. Values must be finite unless
      `allow_nonfinite=True`.
    - `out_dir`: directory for the chunk files, the manifest `sweep.json` and `result.npz`
      (created if missing).
    - `chunk_size`: points per chunk, the unit of work lost on interruption and of the
      progress bar; make it a multiple of the device count and large enough to keep the
      devices busy. None (default): chosen from the measured cost of the work, chunks of
      about `_AUTO_CHUNK_SECONDS` (4 s) with at most `_AUTO_CHUNK_BYTES` (512 MiB) of
      outputs, evaluated in blocks of at most `_AUTO_BLOCK_PER_DEVICE` (65,536) points per
      device; a resumed sweep keeps the size of the run that started it.
    - `batch_size`: if given, each device evaluates its share of a block in steps of
      `batch_size` points (`lax.map` over batches, each batch vmapped), and blocks are
      padded to a multiple of `batch_size` times the device count. The compiled
      per-point code is then the same on any number of devices, so results are bitwise
      independent of the device count. If None, each device vmaps over its whole share in one step.
    - `metadata`: JSON-serialisable `dict` describing the sweep (model, scenario, version
      of your script...). It is stored in the manifest and is part of the fingerprint.
    - `progress`: show a `tqdm` progress bar (points, points/s).
    - `resume`: if True, reuse the finished chunks of an earlier run of the *same* sweep
      in `out_dir`; an `out_dir` that holds a different sweep raises `ValueError`. If
      False, delete the sweep files in `out_dir` (other files are left alone) and start over.
    - `mesh`: the `jax.sharding.Mesh` to run on; the points are sharded over all of its
      axes. Default: a 1-D mesh of `jax.devices()` with axis name `"points"`.
    - `dtype`: if given, cast the real floating-point grid arrays to it (e.g. `np.float32`
      for bulk sweeps in single precision).
    - `allow_nonfinite`: accept NaN and inf in the grid.
    - `on_chunk_done`: called with a [`ChunkInfo`][] after each chunk is final (written, or
      loaded from an earlier run), in that order. An exception raised here stops the sweep;
      the chunks written so far are kept.
    - `keep_chunks`: keep the chunk files after `result.npz` is written (and write the
      last chunk's file too). Default: True when `chunk_size` is given, False for the
      automatic size (the chunk files then exist only while the sweep is unfinished).

    **Returns:**

    The outputs of `fn` for all points: the PyTree `fn` returns, with NumPy arrays of shape
    `(N, ...)` in point order, or `(*grid.shape, ...)` for a [`SweepGrid`][]. The same
    arrays are saved in `out_dir/result.npz`. The whole result is held in host memory: for
    sweeps whose full outputs would not fit, let `fn` return summaries (errors, metrics,
    decimated traces) rather than whole trajectories.

    **Example:**

    ```python
    import jax.numpy as jnp
    import numpy as np
    from pmsmjax.analysis import grid_product, run_sweep

    def fn(p):  # eigenvalues of the dq current dynamics of a PMSM at speed w_m
        R_s, L, w_m = p["R_s"], 2.5e-3, p["w_m"]
        A = jnp.array([[-R_s / L, w_m], [-w_m, -R_s / L]])
        return {"eig": jnp.linalg.eigvals(A)}

    grid = grid_product(R_s=np.linspace(0.5, 1.0, 11), w_m=np.linspace(0.0, 2e3, 101))
    out = run_sweep(fn, grid, out_dir="sweeps/eig", chunk_size=512)
    out["eig"].shape  # (11, 101, 2)
    ```

    !!! note
        Chunk boundaries depend only on the chunk size, never on the device count, so a
        sweep started on one machine can be resumed on another. Every block, the last one
        too, is padded (by repeating its last point) to one common length, a multiple of
        the device count (times `batch_size` if given), so that `fn` is compiled exactly
        once; the padding is discarded.

    !!! note "Reproducibility across device counts"
        With `batch_size=None` the vmap width is a device's share of a block (of a chunk,
        with an explicit `chunk_size`), which depends on the device count. XLA may compile
        a different vmap width differently: on CPU, a max-reduction over a series
        containing inf and NaN returned NaN with a width of 8 but a finite value with a
        width of 16. Finite results were bitwise identical in our
        tests, but this is not guaranteed. Give a `batch_size` (e.g. 32 to 256 on CPU, 1024
        or more on a GPU, dividing `chunk_size / device count`) when results must be bitwise
        identical on any number of devices.

    !!! note
        While a chunk is written (by a writer thread), the next blocks are already running
        on the devices, so disk writes overlap with computation. The compile time is
        recorded separately in the manifest (`compile_seconds`).
    """
    if not callable(fn):
        raise TypeError(f"`run_sweep(fn=...)` must be callable; got {type(fn).__name__}.")
    shape = grid.shape if isinstance(grid, SweepGrid) else None
    host_grid, n_points = _validate_grid(grid, dtype=dtype, allow_nonfinite=allow_nonfinite)
    auto = chunk_size is None
    if not auto:
        if isinstance(chunk_size, bool) or not isinstance(chunk_size, int | np.integer):
            raise ValueError(
                f"`run_sweep(chunk_size=...)` must be an int or None; got {chunk_size!r}."
            )
        if chunk_size < 1:
            raise ValueError(f"`run_sweep(chunk_size=...)` must be >= 1; got {chunk_size}.")
        chunk_size = int(chunk_size)
    keep_chunks = (not auto) if keep_chunks is None else bool(keep_chunks)
    if batch_size is not None:
        if isinstance(batch_size, bool) or not isinstance(batch_size, int | np.integer):
            raise ValueError(f"`run_sweep(batch_size=...)` must be an int; got {batch_size!r}.")
        if batch_size < 1:
            raise ValueError(f"`run_sweep(batch_size=...)` must be >= 1; got {batch_size}.")
        batch_size = int(batch_size)
    metadata_json = _canonical_metadata(metadata)
    if mesh is None:
        mesh = Mesh(np.array(jax.devices()), ("points",))
    elif not isinstance(mesh, Mesh):
        raise TypeError(f"`run_sweep(mesh=...)` must be a jax.sharding.Mesh; got {mesh!r}.")
    out_dir = os.fspath(out_dir)
    is_writer = jax.process_index() == 0

    # Trace `fn` once on abstract scalars: this checks it, gives the output structure, and a
    # hash of its jaxpr so that resuming with a changed `fn` is refused.
    point_spec = {k: jax.ShapeDtypeStruct((), v.dtype) for k, v in host_grid.items()}
    closed_jaxpr, out_shape = jax.make_jaxpr(fn, return_shape=True)(point_spec)
    out_paths, out_treedef = jtu.tree_flatten_with_path(out_shape)
    out_names = _output_names(out_paths)
    out_specs = [leaf for _, leaf in out_paths]
    status_leaves = [
        i
        for i, (path, leaf) in enumerate(out_paths)
        if "status" in _path_parts(path)
        and (np.issubdtype(leaf.dtype, np.integer) or np.issubdtype(leaf.dtype, np.bool_))
    ]

    parts = {
        "grid": _hash_grid(host_grid, shape),
        # the automatic size is chosen once and kept in the manifest and the chunk files
        "chunk_size": "auto" if auto else str(chunk_size),
        "outputs": _hash_text(
            json.dumps([[n, str(s.dtype), list(s.shape)] for n, s in zip(out_names, out_specs)])
        ),
        "metadata": _hash_text(metadata_json),
        "fn": _hash_jaxpr(closed_jaxpr),
    }
    fingerprint = _hash_text(json.dumps(parts, sort_keys=True))

    n_devices = mesh.size
    # Points per compiled evaluation ("block"). With an explicit `chunk_size` a block is a
    # whole chunk, padded to a multiple of the device count (times `batch_size`); with the
    # automatic chunk size it is at most `_AUTO_BLOCK_PER_DEVICE` points per device, and
    # a chunk is as many blocks as last about `_AUTO_CHUNK_SECONDS`. Every block has the
    # same padded length, so `fn` is compiled exactly once, and the block length does not
    # depend on how blocks are grouped into chunks (the same results bit for bit).
    step = n_devices * (batch_size or 1)
    if auto:
        block = min(_round_up(n_points, step),
                    _round_up(_AUTO_BLOCK_PER_DEVICE * n_devices, step))
    else:
        block = _round_up(min(chunk_size, n_points), step)
    out_bytes = sum(int(np.prod(s.shape)) * np.dtype(s.dtype).itemsize for s in out_specs)

    # Decide what to resume on process 0 and broadcast it, so that every process runs the
    # same chunks (and the same collectives) or raises the same error.
    error = scan_error = None
    scan = _Scan(chunk_size=None if auto else chunk_size)
    if is_writer:
        try:
            os.makedirs(out_dir, exist_ok=True)
            error, scan = _scan_out_dir(
                out_dir, fingerprint, parts, n_points, scan.chunk_size, resume
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

    old_manifest = scan.manifest
    old_chunks = (old_manifest or {}).get("chunks", {})
    manifest = _new_manifest(
        fingerprint, parts, metadata, host_grid, shape, n_points, scan.chunk_size, out_names,
        out_specs, mesh, old_manifest,
    )
    manifest.update(chunk_size_auto=auto, block_size=block, keep_chunks=keep_chunks)
    results = [np.empty((n_points, *s.shape), dtype=s.dtype) for s in out_specs]
    keep = ("seconds", "points_per_second", "devices", "batch_size", "finished_at")

    def bounds(i):
        i, c = int(i), int(manifest["chunk_size"])
        return i * c, min((i + 1) * c, n_points)

    def record(info: ChunkInfo, extra: dict, file):
        manifest["chunks"][str(info.index)] = {
            "status": "done",
            "file": file,
            "start": info.start,
            "stop": info.stop,
            "n_nonfinite": info.n_nonfinite,
            "n_failed": info.n_failed,
            **extra,
        }

    def loaded(i, chunk):
        start, stop = bounds(i)
        n_nonfinite, n_failed = _count_bad(chunk, status_leaves, stop - start)
        info = ChunkInfo(int(i), start, stop, True, None, n_nonfinite, n_failed)
        old = old_chunks.get(str(i), {})
        return info, {k: old.get(k) for k in keep}

    if scan.complete:
        # A finished sweep: `result.npz` holds every output; nothing is computed or written.
        arrays = _load_result(os.path.join(out_dir, _RESULT), out_names, fingerprint)
        for res, name in zip(results, out_names):
            res[...] = arrays[name].reshape(res.shape)
        del arrays
        for i in range(manifest["n_chunks"]):
            start, stop = bounds(i)
            info, extra = loaded(i, [r[start:stop] for r in results])
            record(info, extra, old_chunks.get(str(i), {}).get("file"))
            if on_chunk_done is not None:
                on_chunk_done(info)
        return _output_tree(results, shape, out_treedef)

    pbar = prev = result_file = None
    writer = concurrent.futures.ThreadPoolExecutor(1) if is_writer else None
    if is_writer:
        # `result.npz` is begun now: the writer thread writes the grid into it while the
        # devices compute; the outputs follow when every chunk is done.
        result_file = _ResultFile(out_dir)
        result_file.begin(writer, _grid_arrays(host_grid, shape))
    # The manifest is rewritten at most every `_MANIFEST_INTERVAL_S` while chunks finish
    # (the chunk files are the source of truth), and once at the end.
    last_manifest_write = time.perf_counter()
    try:
        # Chunks finished by an earlier run.
        n_done_points = 0
        for i in np.flatnonzero(scan.done):
            start, stop = bounds(i)
            arrays = _load_chunk(os.path.join(out_dir, _chunk_name(i)), out_names, fingerprint)
            for res, name in zip(results, out_names):
                res[start:stop] = arrays[name]
            info, extra = loaded(i, [arrays[n] for n in out_names])
            record(info, extra, _chunk_name(int(i)))
            n_done_points += stop - start
            if on_chunk_done is not None:
                on_chunk_done(info)

        sharding = NamedSharding(mesh, PartitionSpec(mesh.axis_names))
        t0 = time.perf_counter()
        compiled = _compiled_chunk_fn(fn, closed_jaxpr, out_treedef, parts["fn"], mesh, block,
                                      batch_size, host_grid)
        manifest["compile_seconds"] = time.perf_counter() - t0

        pbar = _make_pbar(progress and is_writer, n_points, n_done_points)

        def failed(i, e) -> NoReturn:
            start, stop = bounds(i) if manifest["chunk_size"] else (0, n_points)
            manifest["chunks"][str(i)] = {
                "status": "error", "start": start, "stop": stop, "error": repr(e)[:2000]
            }
            raise RuntimeError(
                f"`run_sweep`: `fn` failed on chunk {i} (points {start} to {stop - 1}). "
                "A failing point must not raise inside `fn`: return NaN or a non-zero "
                "`status` instead (e.g. `simulate(..., throw=False)`). Finished chunks "
                f"are kept in {out_dir!r}; fix `fn` and run again to resume."
            ) from e

        def dispatch(i, s, e):
            """Start points [s, e) of chunk i on the devices (asynchronously)."""
            if e - s == block:  # views of the grid, no copy
                cols = {k: v[s:e] for k, v in host_grid.items()}
            else:  # pad by repeating the last point: real, finite inputs, discarded
                idx = np.minimum(np.arange(s, s + block), e - 1)
                cols = {k: v[idx] for k, v in host_grid.items()}
            # Every process holds the whole grid; the callback is asked only for the slices
            # of this process's own devices.
            inputs = {
                k: jax.make_array_from_callback((block,), sharding, lambda sl, c=c: c[sl])
                for k, c in cols.items()
            }
            try:
                return inputs, compiled(inputs)
            except Exception as err:
                failed(i, err)

        bad = {}  # chunk -> [points with non-finite outputs, with a non-zero status]

        def collect(i, s, e, out):
            """Wait for a block; copy its outputs (padding removed) into `results`."""
            leaves = jtu.tree_leaves(out)
            try:
                if jax.process_count() > 1:
                    host = multihost_utils.process_allgather(leaves, tiled=True)
                else:
                    host = jax.device_get(leaves)
            except Exception as err:
                failed(i, err)
            for res, h in zip(results, host):
                res[s:e] = np.asarray(h)[: e - s]
            pbar.update(e - s)  # the bar moves with every block
            # counted now, while the devices compute the next block
            n_nonfinite, n_failed = _count_bad([r[s:e] for r in results], status_leaves, e - s)
            counts = bad.setdefault(i, [0, None if n_failed is None else 0])
            counts[0] += n_nonfinite
            if n_failed is not None:
                counts[1] += n_failed
            return leaves

        # The automatic chunk size: time the first block, then make a chunk as many blocks
        # as last about `_AUTO_CHUNK_SECONDS`, within `_AUTO_CHUNK_BYTES` of outputs.
        # Process 0 decides for all.
        first = None
        if manifest["chunk_size"] is None:
            e0 = min(block, n_points)
            t_first = time.perf_counter()
            inputs0, out0 = dispatch(0, 0, e0)
            leaves0 = collect(0, 0, e0, out0)
            seconds = time.perf_counter() - t_first
            size = _auto_chunk_size(n_points, block, seconds, out_bytes)
            if jax.process_count() > 1:
                size = int(multihost_utils.broadcast_one_to_all(np.int64(size)))
            manifest["chunk_size"] = size
            manifest["n_chunks"] = math.ceil(n_points / size)
            manifest["first_block_seconds"] = seconds
            first = (e0, inputs0, leaves0)
        n_chunks = manifest["n_chunks"]
        todo = [i for i in range(n_chunks) if not (i < len(scan.done) and scan.done[i])]
        last = todo[-1] if todo else None

        # One queue of blocks over every chunk to do, at most `_DEPTH` of them on the
        # devices at a time: the next blocks run while a finished chunk is counted and
        # handed to the writer thread, which writes it while the devices compute. A chunk
        # is final (`on_chunk_done`) once its file is written, and the next chunk's file is
        # only written after that. The last chunk gets no file unless chunk files are kept:
        # `result.npz`, written at once, holds it.
        queue = collections.deque()
        remaining = {}
        for i in todo:
            start, stop = bounds(i)
            s = first[0] if (first is not None and i == 0) else start
            remaining[i] = stop - s
            for b in range(s, stop, block):
                queue.append((i, b, min(b + block, stop)))
        chunk_io = {} if first is None else {0: first[1:]}
        in_flight = collections.deque()
        t_begin = time.perf_counter() if first is None else t_first
        # prev: (info, extra, future of the file write) of the last finished chunk

        def final(prev):
            nonlocal last_manifest_write
            info, extra, fut = prev
            fut.result()
            record(info, extra, _chunk_name(info.index))
            now = time.perf_counter()
            if is_writer and now - last_manifest_write > _MANIFEST_INTERVAL_S:
                _write_manifest(out_dir, manifest)
                last_manifest_write = now
            notify(info)

        def notify(info):
            pbar.set_postfix_str(f"chunk {info.index + 1}/{n_chunks}", refresh=False)
            if on_chunk_done is not None:
                on_chunk_done(info)

        def chunk_done(i):
            nonlocal t_begin, prev
            start, stop = bounds(i)
            n = stop - start
            chunk = [r[start:stop] for r in results]
            n_nonfinite, n_failed = bad.pop(i)
            inputs, leaves = chunk_io.pop(i)
            now = time.perf_counter()
            seconds, t_begin = now - t_begin, now
            info = ChunkInfo(
                i, start, stop, False, seconds, n_nonfinite, n_failed,
                input_sharding=next(iter(inputs.values())).sharding,
                output_sharding=leaves[0].sharding if leaves else None,
            )
            extra = {
                "seconds": seconds,
                "points_per_second": n / seconds if seconds > 0 else None,
                "devices": n_devices,
                "batch_size": batch_size,
                "finished_at": _now(),
            }
            if prev is not None:  # the previous chunk's file is written: it is final
                p, prev = prev, None
                final(p)
            if keep_chunks or i != last:
                fut = writer.submit(
                    _write_chunk, out_dir, i, dict(zip(out_names, chunk)), fingerprint,
                    metadata_json, start, stop, manifest["chunk_size"],
                ) if is_writer else _DONE
                prev = (info, extra, fut)
            else:
                prev = (info, extra, None)

        def next_block():
            i, s, e, inputs, out = in_flight.popleft()
            leaves = collect(i, s, e, out)
            chunk_io.setdefault(i, (inputs, leaves))
            remaining[i] -= e - s
            if remaining[i] == 0:
                chunk_done(i)

        if first is not None and remaining.get(0) == 0:
            chunk_done(0)
        while queue or in_flight:
            while queue and len(in_flight) < _DEPTH:
                i, s, e = queue.popleft()
                try:
                    inputs, out = dispatch(i, s, e)
                except Exception:
                    while in_flight:  # keep the blocks started before, which did succeed
                        next_block()
                    raise
                in_flight.append((i, s, e, inputs, out))
            next_block()
        if prev is not None:
            p, prev = prev, None
            if p[2] is not None:
                final(p)
            else:  # the last chunk: final once `result.npz` holds it
                record(p[0], p[1], None)
                _complete(results, shape, out_names, result_file, out_dir, manifest,
                          status_leaves, fingerprint, is_writer, keep_chunks)
                notify(p[0])
    except BaseException:
        if prev is not None and prev[2] is not None:
            with contextlib.suppress(Exception):  # keep a chunk whose file was written
                prev[2].result()
                record(prev[0], prev[1], _chunk_name(prev[0].index))
        if result_file is not None:
            writer.shutdown(wait=True)
            result_file.abort()
        raise
    finally:
        if pbar is not None:
            pbar.close()
        if writer is not None:
            writer.shutdown(wait=True)
        if is_writer and not manifest["complete"]:
            manifest["updated"] = _now()
            _write_manifest(out_dir, manifest)

    try:
        if not manifest["complete"]:
            _complete(results, shape, out_names, result_file, out_dir, manifest,
                      status_leaves, fingerprint, is_writer, keep_chunks)
    finally:
        if result_file is not None:
            result_file.abort()  # nothing if it was committed
    return _output_tree(results, shape, out_treedef)


# The last few compiled chunk functions, so that running the same sweep again in one
# session (to resume it, or a second grid of the same size) does not compile again. The key
# holds `id(fn)` and the value `fn` itself, so the id cannot be reused while cached; the
# jaxpr hash makes a changed global or closure that `fn` reads compile anew.
_JIT_CACHE: collections.OrderedDict = collections.OrderedDict()
_JIT_CACHE_SIZE = 8


def _compiled_chunk_fn(fn, closed_jaxpr, out_treedef, fn_hash, mesh, padded, batch_size,
                       host_grid):
    """The compiled function of one padded block, from the cache when the same sweep
    function ran before in this process (lowering a simulation again costs more than a
    small sweep's work). What is compiled is `closed_jaxpr`, the trace of `fn` that
    `run_sweep` already made (for its output structure and hash), evaluated per point
    under `vmap`: `fn`'s Python is not traced a second time (that second trace was a
    fifth of a 4 M-point feasibility command in a fresh process)."""
    dtypes = tuple((k, v.dtype.str) for k, v in host_grid.items())
    key = (id(fn), fn_hash, mesh, padded, batch_size, dtypes)
    if key in _JIT_CACHE:
        _JIT_CACHE.move_to_end(key)
        return _JIT_CACHE[key][1]
    sharding = NamedSharding(mesh, PartitionSpec(mesh.axis_names))
    jitted = jax.jit(
        _chunk_fn(_jaxpr_point_fn(closed_jaxpr, out_treedef), mesh, padded, batch_size),
        in_shardings=sharding, out_shardings=sharding,
    )
    in_spec = {
        k: jax.ShapeDtypeStruct((padded,), v.dtype, sharding=sharding)
        for k, v in host_grid.items()
    }
    compiled = jitted.lower(in_spec).compile()
    _JIT_CACHE[key] = (fn, compiled)  # holds `fn`: its id stays unique
    while len(_JIT_CACHE) > _JIT_CACHE_SIZE:
        _JIT_CACHE.popitem(last=False)
    return compiled


def _jaxpr_point_fn(closed_jaxpr, out_treedef):
    """The per-point function that `closed_jaxpr` (`make_jaxpr` of `fn` on one point,
    its inputs the grid's values in `tree_leaves` order, i.e. sorted names) computes,
    with `fn`'s output structure."""
    run = jax.extend.core.jaxpr_as_fun(closed_jaxpr)

    def point(p):
        return jtu.tree_unflatten(out_treedef, run(*jtu.tree_leaves(p)))

    return point


def _chunk_fn(fn, mesh, padded, batch_size):
    """The function of one whole (padded) chunk that is compiled."""
    if batch_size is None:
        return jax.vmap(fn)
    n_devices = mesh.size
    blocks = NamedSharding(mesh, PartitionSpec(mesh.axis_names, None, None))

    def chunk_fn(inputs):
        # (padded,) -> (devices, blocks per device, batch_size): device j holds row j, so
        # the reshape moves no data. vmap over the device axis (width 1 per device) of a
        # lax.map over blocks of a vmap of width batch_size: every device runs the same loop
        # body whatever the device count.
        xs = jtu.tree_map(lambda x: x.reshape(n_devices, -1, batch_size), inputs)
        xs = jax.lax.with_sharding_constraint(xs, blocks)
        ys = jax.vmap(lambda x: jax.lax.map(jax.vmap(fn), x))(xs)
        return jtu.tree_map(lambda y: y.reshape(padded, *y.shape[3:]), ys)

    return chunk_fn


# --------------------------------------------------------------------------------------
# Validation


def _as_numeric(where: str, values) -> np.ndarray:
    if isinstance(values, jax.core.Tracer):
        raise ValueError(f"`{where}` is a JAX tracer; `run_sweep` cannot run under jit/vmap.")
    try:
        a = np.asarray(values)
    except Exception as e:  # ragged lists and the like
        raise ValueError(f"`{where}` is not an array: {e}") from None
    if not (
        np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.bool_)
    ) or a.dtype.kind == "O":
        raise ValueError(f"`{where}` must hold numbers; got dtype {a.dtype}.")
    return a


def _validate_grid(grid, *, dtype, allow_nonfinite):
    if not isinstance(grid, Mapping):
        raise TypeError(
            "`run_sweep(grid=...)` must be a dict of 1-D arrays (or `grid_product(...)`); "
            f"got {type(grid).__name__}."
        )
    if len(grid) == 0:
        raise ValueError("`run_sweep(grid=...)` is empty: it needs at least one key.")
    host = {}
    for key, values in grid.items():
        if not isinstance(key, str):
            raise ValueError(f"`run_sweep(grid=...)` keys must be strings; got {key!r}.")
        where = f"grid[{key!r}]"
        a = _as_numeric(where, values)
        if a.ndim != 1:
            raise ValueError(
                f"`{where}` must be a 1-D array of point values; got shape {a.shape}. "
                "Use `grid_product(...)` for a Cartesian product of axes, or `np.full(N, x)` "
                "for a constant (or close over constants in `fn`)."
            )
        if a.size == 0:
            raise ValueError(f"`{where}` is empty: a sweep needs at least one point.")
        if dtype is not None and np.issubdtype(a.dtype, np.floating):
            a = a.astype(dtype)
        # What JAX will actually compute with (float64 -> float32 unless x64 is enabled).
        a = np.ascontiguousarray(a, dtype=jax.dtypes.canonicalize_dtype(a.dtype))
        if not allow_nonfinite and np.issubdtype(a.dtype, np.inexact):
            bad = np.flatnonzero(~np.isfinite(a))
            if bad.size:
                raise ValueError(
                    f"`{where}` has {bad.size} non-finite value(s), the first at index "
                    f"{bad[0]} ({a[bad[0]]!r}). Pass `allow_nonfinite=True` if that is meant."
                )
        host[key] = a
    lengths = {k: v.size for k, v in host.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(
            "`run_sweep(grid=...)` arrays must all have the same length (one entry per point); "
            f"got lengths {lengths}."
        )
    return host, next(iter(lengths.values()))


def _canonical_metadata(metadata) -> str:
    if metadata is None:
        metadata = {}
    if not isinstance(metadata, Mapping):
        raise ValueError(f"`run_sweep(metadata=...)` must be a dict; got {type(metadata)}.")

    def default(x):
        if isinstance(x, np.generic):
            return x.item()
        if isinstance(x, np.ndarray | jax.Array):
            return np.asarray(x).tolist()
        raise TypeError(f"{type(x).__name__} is not JSON-serialisable")

    try:
        return json.dumps(metadata, sort_keys=True, default=default, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise ValueError(
            f"`run_sweep(metadata=...)` must be JSON-serialisable (str, numbers, bools, None, "
            f"lists and dicts; finite floats): {e}."
        ) from None


# --------------------------------------------------------------------------------------
# Fingerprints


def _hash_text(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def _hash_grid(host_grid, shape) -> str:
    h = hashlib.sha256()
    h.update(json.dumps(list(shape) if shape is not None else None).encode())
    for key in sorted(host_grid):
        a = host_grid[key]
        h.update(json.dumps([key, a.dtype.str, a.size]).encode())
        h.update(memoryview(a).cast("B"))  # the bytes of `a.tobytes()`, without a copy
    return h.hexdigest()


# Hashes of the printed jaxprs of recent sweeps, by the jaxpr object: `make_jaxpr` of the
# same function returns the same (cached) jaxpr, and printing a large one (a simulation)
# costs more than a small sweep's work.
_JAXPR_TEXT_HASH: collections.OrderedDict = collections.OrderedDict()


def _hash_jaxpr(closed_jaxpr) -> str:
    jaxpr = closed_jaxpr.jaxpr
    key = id(jaxpr)
    if key in _JAXPR_TEXT_HASH and _JAXPR_TEXT_HASH[key][0] is jaxpr:
        _JAXPR_TEXT_HASH.move_to_end(key)
        h = _JAXPR_TEXT_HASH[key][1].copy()
    else:
        # jax prints function addresses as 0xXXXXXXXXXXXX already; strip any left to be
        # sure, so that the hash is stable between processes.
        text = re.sub(r"0x[0-9a-fA-F]{6,}", "0x", str(jaxpr))
        h = hashlib.sha256(text.encode())
        _JAXPR_TEXT_HASH[key] = (jaxpr, h.copy())  # holds `jaxpr`: its id stays unique
        while len(_JAXPR_TEXT_HASH) > _JIT_CACHE_SIZE:
            _JAXPR_TEXT_HASH.popitem(last=False)
    for c in closed_jaxpr.consts:  # closed-over arrays (e.g. parameters) are not printed
        c = np.asarray(c)
        h.update(f"{c.dtype.str}{c.shape}".encode())
        h.update(np.ascontiguousarray(c).tobytes())
    return h.hexdigest()


# --------------------------------------------------------------------------------------
# Outputs


def _path_parts(path) -> list[str]:
    parts = []
    for k in path:
        if isinstance(k, jtu.DictKey):
            parts.append(str(k.key))
        elif isinstance(k, jtu.GetAttrKey):
            parts.append(k.name)
        elif isinstance(k, jtu.SequenceKey):
            parts.append(str(k.idx))
        elif isinstance(k, jtu.FlattenedIndexKey):
            parts.append(str(k.key))
        else:
            parts.append(str(k))
    return parts


def _output_names(out_paths) -> list[str]:
    names = []
    for path, leaf in out_paths:
        name = "/".join(_path_parts(path)) or "output"
        if not isinstance(leaf, jax.ShapeDtypeStruct):
            raise ValueError(f"`run_sweep`: output {name!r} of `fn` is not an array: {leaf!r}.")
        if name.startswith("__") or name == "grid" or name.startswith("grid/"):
            raise ValueError(
                f"`run_sweep`: output name {name!r} is reserved (names starting with '__' or "
                "'grid/' are used in the sweep files); rename it."
            )
        if name in names:
            raise ValueError(f"`run_sweep`: two outputs of `fn` are both named {name!r}.")
        names.append(name)
    return names


def _count_bad(arrays, status_leaves, n) -> tuple[int, int | None]:
    """Points (of the first `n`) with a non-finite output, and with a non-zero status."""
    nonfinite = np.zeros(n, dtype=bool)
    for a in arrays:
        if np.issubdtype(a.dtype, np.inexact):
            nonfinite |= ~np.isfinite(a.reshape(n, -1)).all(axis=1)
    if not status_leaves:
        return int(nonfinite.sum()), None
    failed = np.zeros(n, dtype=bool)
    for i in status_leaves:
        failed |= (arrays[i].reshape(n, -1) != 0).any(axis=1)
    return int(nonfinite.sum()), int(failed.sum())


# --------------------------------------------------------------------------------------
# Files


def _chunk_name(i: int) -> str:
    return f"chunk_{i:06d}.npz"


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _atomic_write(path: str, write: Callable, *, durable: bool = True) -> None:
    """Write `path` via a hidden temporary file in the same directory and `os.replace`;
    `durable`: flushed to the disk (`fsync`) before the rename, and the rename too."""
    d, base = os.path.split(path)
    # Not `tempfile.mkstemp`: its files are private (0600); this one obeys the umask.
    tmp = os.path.join(d, f".{base}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            if durable:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise
    if not durable:
        return
    with contextlib.suppress(OSError, AttributeError):  # make the rename durable (POSIX)
        dfd = os.open(d or ".", os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


def _write_chunk(out_dir, i, arrays, fingerprint, metadata_json, start, stop, chunk_size):
    meta = {
        "__chunk_size__": np.array(chunk_size),
        "__fingerprint__": np.array(fingerprint),
        "__metadata__": np.array(metadata_json),
        "__chunk__": np.array(i),
        "__start__": np.array(start),
        "__stop__": np.array(stop),
    }
    _atomic_write(os.path.join(out_dir, _chunk_name(i)), lambda f: np.savez(f, **arrays, **meta))


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


def _write_manifest(out_dir, manifest):
    manifest["chunks"] = dict(sorted(manifest["chunks"].items(), key=lambda kv: int(kv[0])))
    text = json.dumps(manifest, indent=1, allow_nan=False)
    # Not flushed to the disk (`fsync`): while a sweep runs the chunk files, which are,
    # are the source of truth.
    _atomic_write(os.path.join(out_dir, _MANIFEST), lambda f: f.write(text.encode()),
                  durable=False)


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
                stacklevel=3,
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
                stacklevel=3,
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
        expected = (i * scan.chunk_size, min((i + 1) * scan.chunk_size, n_points))
        if i >= n_chunks or (start, stop) != expected:
            return _mismatch_error(out_dir, [f"chunk file {name}"]), scan
        scan.done[i] = True
    return None, scan


def _round_up(n: int, step: int) -> int:
    return math.ceil(n / step) * step


def _auto_chunk_size(n_points, block, block_seconds, out_bytes) -> int:
    """Points per chunk for the automatic size: whole blocks, about
    `_AUTO_CHUNK_SECONDS` of work at the first block's measured rate, at most
    `_AUTO_CHUNK_BYTES` of outputs (and at least one block), and the points shared evenly
    between the chunks (the last one is not a small remainder)."""
    per_point = max(block_seconds, 1e-9) / block
    target = _AUTO_CHUNK_SECONDS / per_point
    target = min(target, _AUTO_CHUNK_BYTES / max(out_bytes, 1))
    size = max(block, int(target) // block * block)
    if size >= n_points:
        return _round_up(n_points, block)
    n_chunks = math.ceil(n_points / size)
    return _round_up(math.ceil(n_points / n_chunks), block)


def _load_result(path, out_names, fingerprint) -> dict[str, np.ndarray]:
    return _load_outputs(path, out_names, fingerprint, "the finished sweep's")


def _output_tree(results, shape, out_treedef):
    if shape is not None:
        results = [r.reshape(*shape, *r.shape[1:]) for r in results]
    return jtu.tree_unflatten(out_treedef, results)


def _grid_arrays(host_grid, shape) -> dict[str, np.ndarray]:
    return {f"grid/{k}": v if shape is None else v.reshape(shape) for k, v in host_grid.items()}


class _ResultFile:
    """`result.npz` (as `np.savez` writes it: uncompressed `.npy` members of a zip file),
    written in parts to a hidden temporary file that is renamed when complete."""

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
        for name, a in arrays.items():
            with self.zip.open(name + ".npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(a), allow_pickle=False)

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
            with contextlib.suppress(OSError, AttributeError):  # the rename (POSIX)
                dfd = os.open(os.path.dirname(self.path) or ".", os.O_RDONLY)
                try:
                    os.fsync(dfd)
                finally:
                    os.close(dfd)

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


def _complete(results, shape, out_names, result_file, out_dir, manifest, status_leaves,
              fingerprint, is_writer, keep_chunks):
    """Write `result.npz` and the complete manifest (process 0), then delete the chunk
    files unless they are kept: the result holds all of them. `result.npz` is flushed to
    the disk (`fsync`) when it replaces chunk files; when no chunk file was written (one
    chunk), it is written like the command's other outputs."""
    manifest["complete"] = True
    if not is_writer:
        return
    arrays = dict(zip(out_names, results))
    if shape is not None:
        arrays = {k: v.reshape(*shape, *v.shape[1:]) for k, v in arrays.items()}
    chunk_files = [name for name in os.listdir(out_dir) if _CHUNK_RE.match(name)]
    result_file.commit({**arrays, "__fingerprint__": np.array(fingerprint)},
                       durable=bool(chunk_files) and not keep_chunks)
    manifest["n_nonfinite"] = sum(c["n_nonfinite"] for c in manifest["chunks"].values())
    failed = [c["n_failed"] for c in manifest["chunks"].values()]
    manifest["n_failed"] = None if not status_leaves else sum(failed)
    if not keep_chunks:
        for c in manifest["chunks"].values():
            c["file"] = None
    manifest["updated"] = _now()
    _write_manifest(out_dir, manifest)
    if not keep_chunks:
        for name in chunk_files:
            with contextlib.suppress(FileNotFoundError):
                os.remove(os.path.join(out_dir, name))


def _versions():
    versions = {"python": platform.python_version()}
    for pkg in ("pmsmjax", "jax", "jaxlib", "numpy"):
        try:
            versions[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:  # pragma: no cover
            versions[pkg] = None
    return versions


def _new_manifest(
    fingerprint, parts, metadata, host_grid, shape, n_points, chunk_size, out_names,
    out_specs, mesh, old,
):
    devices = mesh.devices.reshape(-1)
    n_chunks = None if chunk_size is None else math.ceil(n_points / chunk_size)
    return {
        "format": _FORMAT,
        "fingerprint": fingerprint,
        "fingerprint_parts": parts,
        "metadata": json.loads(_canonical_metadata(metadata)),
        "n_points": n_points,
        "chunk_size": chunk_size,
        "n_chunks": n_chunks,
        "grid": {k: str(v.dtype) for k, v in host_grid.items()},
        "grid_shape": list(shape) if shape is not None else None,
        "outputs": {
            n: {"dtype": str(s.dtype), "shape": list(s.shape)}
            for n, s in zip(out_names, out_specs)
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


def _n_todo(todo, bounds) -> int:
    return sum(bounds[i][1] - bounds[i][0] for i in todo)


def _make_pbar(enabled, total, initial):
    from tqdm import tqdm

    return tqdm(
        total=total, initial=initial, unit="pt", unit_scale=True, desc="sweep",
        disable=not enabled, dynamic_ncols=True,
    )
