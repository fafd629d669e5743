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

The files in `out_dir` (the chunk files, the manifest `sweep.json` and `result.npz`, all
written atomically) are described in `pmsmjax.analysis._sweep_files`: the chunk files are
the source of truth while a sweep runs, and running a complete sweep again reads
`result.npz` and computes nothing. Run one sweep per `out_dir` at a time.

**Several hosts.** Start the same script on every host and call
`jax.distributed.initialize()` before any other JAX call (on SLURM or Cloud TPU it finds
the coordinator itself; otherwise pass `coordinator_address="host0:1234"`,
`num_processes=P` and `process_id=p`). Every process must build the same grid. The points
of a product grid (`grid_product`) are made on the devices from its axes; of any other
grid, each process places the slices of every block that belong to its own devices
(`jax.make_array_from_callback`). The chunk runs SPMD over all devices, and the outputs are
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
import math
import os
import time
from collections.abc import Callable, Mapping
from typing import Any

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh

from ._sweep_devices import _compiled_chunk_fn, _Devices
from ._sweep_files import (
    _RESULT,
    _chunk_bounds,
    _chunk_name,
    _complete,
    _grid_arrays,
    _load_chunk,
    _load_result,
    _new_manifest,
    _now,
    _record,
    _ResultFile,
    _write_chunk,
    _write_manifest,
)
from ._sweep_resume import _resume_scan
from ._sweep_spec import _count_bad, _output_tree, _sweep_spec


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
# What the manifest keeps of a chunk that an earlier run finished.
_KEEP = ("seconds", "points_per_second", "devices", "batch_size", "finished_at")


@dataclasses.dataclass(frozen=True)
class ChunkInfo:
    """What [`run_sweep`][] passes to `on_chunk_done` after each chunk is final.

    - `index`: chunk number, from 0.
    - `start`, `stop`: the chunk covers grid points `start <= i < stop`.
    - `loaded`: True if the chunk was read from an earlier run's file, False if computed now.
    - `seconds`: wall time of the chunk (s); `None` when loaded.
    - `n_nonfinite`: points of the chunk with a NaN or inf in any output.
    - `n_failed`: points with a non-zero `status` output; `None` if `fn` returns no status.
    - `input_sharding`, `output_sharding`: the shardings of the chunk's points on the
      devices (those of a product grid are made there, from its axes) and of its output
      arrays (one leaf each); `None` when loaded.
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
    keep_result: bool = True,
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
    - `keep_result`: write `result.npz` when the sweep is finished, so that running it
      again only reads it. False: a finished sweep keeps its manifest alone (the caller
      stores what it needs of the outputs, as `pmsmjax feasibility` does in its own file);
      an interrupted one still resumes from its chunk files.

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
    spec = _sweep_spec(fn, grid, out_dir=out_dir, chunk_size=chunk_size,
                       batch_size=batch_size, metadata=metadata, mesh=mesh, dtype=dtype,
                       allow_nonfinite=allow_nonfinite, keep_chunks=keep_chunks,
                       keep_result=keep_result)
    block = _block_length(spec)
    scan = _resume_scan(spec, resume)
    manifest = _new_manifest(spec, scan.chunk_size, scan.manifest)
    manifest.update(chunk_size_auto=spec.auto, block_size=block, keep_chunks=spec.keep_chunks)
    old_chunks = (scan.manifest or {}).get("chunks", {})
    results = [np.empty((spec.n_points, *s.shape), dtype=s.dtype) for s in spec.out_specs]
    if scan.complete:
        _read_complete(spec, manifest, old_chunks, results, on_chunk_done)
    else:
        _compute(spec, block, scan, manifest, old_chunks, results, progress, on_chunk_done)
    return _output_tree(results, spec.shape, spec.out_treedef)


def _block_length(spec) -> int:
    """Points per compiled evaluation ("block"). With an explicit `chunk_size` a block is a
    whole chunk, padded to a multiple of the device count (times `batch_size`); with the
    automatic chunk size it is at most `_AUTO_BLOCK_PER_DEVICE` points per device, and a
    chunk is as many blocks as last about `_AUTO_CHUNK_SECONDS`. Every block has the same
    padded length, so `fn` is compiled exactly once, and the block length does not depend
    on how blocks are grouped into chunks (the same results bit for bit)."""
    n_devices, n_points = spec.mesh.size, spec.n_points
    step = n_devices * (spec.batch_size or 1)
    if spec.auto:
        return min(_round_up(n_points, step),
                   _round_up(_AUTO_BLOCK_PER_DEVICE * n_devices, step))
    return _round_up(min(spec.chunk_size, n_points), step)


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


def _loaded(spec, manifest, old_chunks, i, chunk):
    """The `ChunkInfo` of chunk `i` as read from an earlier run (its outputs `chunk`), and
    what the manifest keeps of the earlier run's entry for it."""
    start, stop = _chunk_bounds(i, manifest["chunk_size"], spec.n_points)
    n_nonfinite, n_failed = _count_bad(chunk, spec.status_leaves, stop - start)
    info = ChunkInfo(int(i), start, stop, True, None, n_nonfinite, n_failed)
    old = old_chunks.get(str(i), {})
    return info, {k: old.get(k) for k in _KEEP}


def _read_complete(spec, manifest, old_chunks, results, on_chunk_done):
    """A finished sweep: `result.npz` holds every output; nothing is computed or written."""
    arrays = _load_result(os.path.join(spec.out_dir, _RESULT), spec.out_names,
                          spec.fingerprint)
    for res, name in zip(results, spec.out_names):
        res[...] = arrays[name].reshape(res.shape)
    del arrays
    for i in range(manifest["n_chunks"]):
        start, stop = _chunk_bounds(i, manifest["chunk_size"], spec.n_points)
        info, extra = _loaded(spec, manifest, old_chunks, i, [r[start:stop] for r in results])
        _record(manifest, info, extra, old_chunks.get(str(i), {}).get("file"))
        if on_chunk_done is not None:
            on_chunk_done(info)


def _read_done_chunks(spec, manifest, scan, old_chunks, results, on_chunk_done) -> int:
    """Read the chunks that an earlier run finished into `results`; returns their points."""
    n_done_points = 0
    for i in np.flatnonzero(scan.done):
        start, stop = _chunk_bounds(i, manifest["chunk_size"], spec.n_points)
        arrays = _load_chunk(os.path.join(spec.out_dir, _chunk_name(i)), spec.out_names,
                             spec.fingerprint)
        for res, name in zip(results, spec.out_names):
            res[start:stop] = arrays[name]
        info, extra = _loaded(spec, manifest, old_chunks, i,
                              [arrays[n] for n in spec.out_names])
        _record(manifest, info, extra, _chunk_name(int(i)))
        n_done_points += stop - start
        if on_chunk_done is not None:
            on_chunk_done(info)
    return n_done_points


def _compute(spec, block, scan, manifest, old_chunks, results, progress, on_chunk_done):
    """Compute the chunks that no earlier run finished (after reading those that one did)
    into `results`, and write the chunk files, `result.npz` and the manifest (process 0)."""
    is_writer = spec.is_writer
    pbar = chunks = result_file = None
    writer = concurrent.futures.ThreadPoolExecutor(1) if is_writer else None
    if is_writer and spec.keep_result:
        # `result.npz` is begun now: the writer thread writes the grid into it while the
        # devices compute; the outputs follow when every chunk is done.
        result_file = _ResultFile(spec.out_dir)
        result_file.begin(writer, _grid_arrays(spec.host_grid, spec.shape))
    # The manifest is rewritten at most every `_MANIFEST_INTERVAL_S` while chunks finish
    # (the chunk files are the source of truth), and once at the end.
    t_start = time.perf_counter()
    try:
        n_done_points = _read_done_chunks(spec, manifest, scan, old_chunks, results,
                                          on_chunk_done)
        t0 = time.perf_counter()
        compiled = _compiled_chunk_fn(spec.fn, spec.closed_jaxpr, spec.out_treedef,
                                      spec.parts["fn"], spec.mesh, block, spec.batch_size,
                                      spec.host_grid, spec.axes, spec.shape)
        manifest["compile_seconds"] = time.perf_counter() - t0
        pbar = _make_pbar(progress and is_writer, spec.n_points, n_done_points)
        devices = _Devices(spec, compiled, block, results, pbar, manifest)
        first = None
        if manifest["chunk_size"] is None:
            first = _first_block(spec, devices, block, manifest)
        n_chunks = manifest["n_chunks"]
        todo = [i for i in range(n_chunks) if not (i < len(scan.done) and scan.done[i])]
        queue, remaining = _plan_blocks(spec, manifest, todo, block, first)
        t_begin = time.perf_counter() if first is None else first[3]
        chunks = _Chunks(spec, manifest, results, devices.bad, writer, pbar, on_chunk_done,
                         n_chunks, todo, remaining, first, t_begin, t_start)
        if first is not None and remaining.get(0) == 0:
            chunks.chunk_done(0)
        _run_blocks(devices, chunks, queue)
        chunks.finish(result_file)
    except BaseException:
        if chunks is not None:
            chunks.keep_written()
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
            _write_manifest(spec.out_dir, manifest)

    try:
        if not manifest["complete"]:
            _complete(spec, results, result_file, manifest)
    finally:
        if result_file is not None:
            result_file.abort()  # nothing if it was committed


def _first_block(spec, devices, block, manifest):
    """The automatic chunk size: time the first block, then make a chunk as many blocks as
    last about `_AUTO_CHUNK_SECONDS`, within `_AUTO_CHUNK_BYTES` of outputs; process 0
    decides for all. Returns `(stop, in_sharding, leaves, t)`: the first block's end, the
    sharding of its points, its outputs, and when it began (`time.perf_counter`, s)."""
    n_points = spec.n_points
    e0 = min(block, n_points)
    t_first = time.perf_counter()
    in_sharding0, out0 = devices.dispatch(0, 0, e0)
    leaves0 = devices.collect(0, 0, e0, out0)
    seconds = time.perf_counter() - t_first
    size = _auto_chunk_size(n_points, block, seconds, spec.out_bytes)
    if jax.process_count() > 1:
        size = int(multihost_utils.broadcast_one_to_all(np.int64(size)))
    manifest["chunk_size"] = size
    manifest["n_chunks"] = math.ceil(n_points / size)
    manifest["first_block_seconds"] = seconds
    return e0, in_sharding0, leaves0, t_first


def _plan_blocks(spec, manifest, todo, block, first):
    """The blocks `(chunk, start, stop)` of the chunks `todo`, in order (after the first
    block when `first` ran it), and the points each of those chunks has still to do."""
    queue = collections.deque()
    remaining = {}
    for i in todo:
        start, stop = _chunk_bounds(i, manifest["chunk_size"], spec.n_points)
        s = first[0] if (first is not None and i == 0) else start
        remaining[i] = stop - s
        for b in range(s, stop, block):
            queue.append((i, b, min(b + block, stop)))
    return queue, remaining


def _run_blocks(devices, chunks, queue):
    """One queue of blocks over every chunk to do, at most `_DEPTH` of them on the devices
    at a time: the next blocks run while a finished chunk is counted and handed to the
    writer thread, which writes it while the devices compute (`_Chunks`)."""
    in_flight = collections.deque()
    while queue or in_flight:
        while queue and len(in_flight) < _DEPTH:
            i, s, e = queue.popleft()
            try:
                in_sharding, out = devices.dispatch(i, s, e)
            except Exception:
                while in_flight:  # keep the blocks started before, which did succeed
                    _next_block(devices, chunks, in_flight)
                raise
            in_flight.append((i, s, e, in_sharding, out))
        _next_block(devices, chunks, in_flight)


def _next_block(devices, chunks, in_flight):
    """Wait for the oldest block on the devices and hand it to its chunk."""
    i, s, e, in_sharding, out = in_flight.popleft()
    leaves = devices.collect(i, s, e, out)
    chunks.block_done(i, s, e, in_sharding, leaves)


class _Chunks:
    """The chunks being computed, made final in order. A chunk whose blocks are all
    collected is handed to the writer thread, which writes its file while the devices
    compute; it is final (entered in the manifest, `on_chunk_done`) once its file is
    written, and the next chunk's file is only written after that. The last chunk gets no
    file unless chunk files are kept: `result.npz`, written at once, holds it.

    **Arguments:**

    - `spec`, `manifest`, `results`: the `_SweepSpec`, its manifest and its outputs.
    - `bad`: `_Devices.bad`, the counts of bad points per chunk.
    - `writer`: the writer thread (None on processes other than 0, which write nothing);
      `pbar`: the progress bar; `on_chunk_done`: as in [`run_sweep`][].
    - `n_chunks`, `todo`: the number of chunks, and the chunks to compute.
    - `remaining`: the points each chunk of `todo` has still to do (`_plan_blocks`).
    - `first`: `_first_block`'s result when it ran the first block, else None.
    - `t_begin`: when the first chunk began; `t_start`: when the sweep began (both
      `time.perf_counter`, s).
    """

    def __init__(self, spec, manifest, results, bad, writer, pbar, on_chunk_done, n_chunks,
                 todo, remaining, first, t_begin, t_start):
        self.spec, self.manifest, self.results, self.bad = spec, manifest, results, bad
        self.writer, self.pbar, self.on_chunk_done = writer, pbar, on_chunk_done
        self.n_chunks, self.remaining = n_chunks, remaining
        self.last = todo[-1] if todo else None
        self.t_begin, self.last_manifest_write = t_begin, t_start
        # chunk -> the sharding of the points and the outputs of its first block
        self.io = {} if first is None else {0: first[1:3]}
        self.prev = None  # (info, extra, future of the file write) of the last finished chunk

    def block_done(self, i, s, e, in_sharding, leaves):
        """The block [s, e) of chunk i is collected; the chunk is done with its last."""
        self.io.setdefault(i, (in_sharding, leaves))
        self.remaining[i] -= e - s
        if self.remaining[i] == 0:
            self.chunk_done(i)

    def chunk_done(self, i):
        spec, manifest = self.spec, self.manifest
        start, stop = _chunk_bounds(i, manifest["chunk_size"], spec.n_points)
        n = stop - start
        chunk = [r[start:stop] for r in self.results]
        n_nonfinite, n_failed = self.bad.pop(i)
        in_sharding, leaves = self.io.pop(i)
        now = time.perf_counter()
        seconds, self.t_begin = now - self.t_begin, now
        info = ChunkInfo(
            i, start, stop, False, seconds, n_nonfinite, n_failed,
            input_sharding=in_sharding,
            output_sharding=leaves[0].sharding if leaves else None,
        )
        extra = {
            "seconds": seconds,
            "points_per_second": n / seconds if seconds > 0 else None,
            "devices": spec.mesh.size,
            "batch_size": spec.batch_size,
            "finished_at": _now(),
        }
        if self.prev is not None:  # the previous chunk's file is written: it is final
            p, self.prev = self.prev, None
            self.final(p)
        if spec.keep_chunks or i != self.last:
            fut = self.writer.submit(
                _write_chunk, spec.out_dir, i, dict(zip(spec.out_names, chunk)),
                spec.fingerprint, spec.metadata_json, start, stop, manifest["chunk_size"],
            ) if spec.is_writer else _DONE
            self.prev = (info, extra, fut)
        else:
            self.prev = (info, extra, None)

    def final(self, prev):
        """The chunk `prev` (`self.prev` before) is final once its file is written."""
        info, extra, fut = prev
        fut.result()
        _record(self.manifest, info, extra, _chunk_name(info.index))
        now = time.perf_counter()
        if self.spec.is_writer and now - self.last_manifest_write > _MANIFEST_INTERVAL_S:
            _write_manifest(self.spec.out_dir, self.manifest)
            self.last_manifest_write = now
        self.notify(info)

    def notify(self, info):
        self.pbar.set_postfix_str(f"chunk {info.index + 1}/{self.n_chunks}", refresh=False)
        if self.on_chunk_done is not None:
            self.on_chunk_done(info)

    def finish(self, result_file):
        """Make the last chunk final: once its file is written, or, without a file of its
        own, once `result.npz` (`result_file`) holds it."""
        if self.prev is None:
            return
        p, self.prev = self.prev, None
        if p[2] is not None:
            self.final(p)
        else:
            _record(self.manifest, p[0], p[1], None)
            _complete(self.spec, self.results, result_file, self.manifest)
            self.notify(p[0])

    def keep_written(self):
        """After an error: keep the last finished chunk if its file was written."""
        prev = self.prev
        if prev is not None and prev[2] is not None:
            with contextlib.suppress(Exception):
                prev[2].result()
                _record(self.manifest, prev[0], prev[1], _chunk_name(prev[0].index))


def _make_pbar(enabled, total, initial):
    from tqdm import tqdm

    return tqdm(
        total=total, initial=initial, unit="pt", unit_scale=True, desc="sweep",
        disable=not enabled, dynamic_ncols=True,
    )
