"""The devices' side of a sweep ([`run_sweep`][]): `fn` compiled once for a block of points
sharded over all devices of a `jax.sharding.Mesh` (under `jax.distributed`, the devices
of every process), each block placed and started asynchronously, and its outputs gathered
back to every process.

A block's points are placed in one of two ways. A product of axes (`grid_product`) is
made on the devices: the compiled block takes the block's first and last point indices
and the axes (on every device, placed once per sweep), and each device computes the
indices of its share and gathers their axis values: the host's points are neither checked
nor copied (for 4 M points, 96 MB of float64 block by block before). Any other grid is
sent block by block: every process supplies the slices of its own devices."""

from __future__ import annotations

import collections
import math
from typing import NoReturn

import jax
import jax.extend
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import NamedSharding, PartitionSpec

from ._sweep_files import _chunk_bounds
from ._sweep_spec import _count_bad


# The last few compiled chunk functions, so that running the same sweep again in one
# session (to resume it, or a second grid of the same size) does not compile again. The key
# holds `id(fn)` and the value `fn` itself, so the id cannot be reused while cached; the
# jaxpr hash makes a changed global or closure that `fn` reads compile anew.
_JIT_CACHE: collections.OrderedDict = collections.OrderedDict()
_JIT_CACHE_SIZE = 8


def _compiled_chunk_fn(fn, closed_jaxpr, out_treedef, fn_hash, mesh, padded, batch_size,
                       host_grid, axes=None, shape=None):
    """The compiled function of one padded block, from the cache when the same sweep
    function ran before in this process (lowering a simulation again costs more than a
    small sweep's work). What is compiled is `closed_jaxpr`, the trace of `fn` that
    `run_sweep` already made (for its output structure and hash), evaluated per point
    under `vmap`: `fn`'s Python is not traced a second time (that second trace was a
    fifth of a 4 M-point feasibility command in a fresh process).

    With `axes` (a product grid of `shape`, `SweepGrid.product_axes` checked) the compiled
    function is `f(bounds, axes)` (`_indexed`); else `f(points)` of the block's points."""
    dtypes = tuple((k, v.dtype.str) for k, v in host_grid.items())
    key = (id(fn), fn_hash, mesh, padded, batch_size, dtypes,
           None if axes is None else tuple(shape))
    if key in _JIT_CACHE:
        _JIT_CACHE.move_to_end(key)
        return _JIT_CACHE[key][1]
    sharding = NamedSharding(mesh, PartitionSpec(mesh.axis_names))
    chunk_fn = _chunk_fn(_jaxpr_point_fn(closed_jaxpr, out_treedef), mesh, padded,
                         batch_size)
    if axes is None:
        jitted = jax.jit(chunk_fn, in_shardings=sharding, out_shardings=sharding)
        in_spec = ({k: jax.ShapeDtypeStruct((padded,), v.dtype, sharding=sharding)
                    for k, v in host_grid.items()},)
    else:
        everywhere = NamedSharding(mesh, PartitionSpec())
        jitted = jax.jit(_indexed(chunk_fn, sharding, padded, shape, tuple(axes)),
                         in_shardings=everywhere, out_shardings=sharding)
        in_spec = (jax.ShapeDtypeStruct((2,), _index_dtype(), sharding=everywhere),
                   {k: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=everywhere)
                    for k, a in axes.items()})
    compiled = jitted.lower(*in_spec).compile()
    _JIT_CACHE[key] = (fn, compiled)  # holds `fn`: its id stays unique
    while len(_JIT_CACHE) > _JIT_CACHE_SIZE:
        _JIT_CACHE.popitem(last=False)
    return compiled


def _index_dtype():
    """Point indices on the devices: 64-bit with float64 on (JAX has 64-bit integers only
    then), else 32-bit (`run_sweep` sends larger grids point by point)."""
    return np.int64 if jax.config.jax_enable_x64 else np.int32


def _indexed(chunk_fn, sharding, padded, shape, names):
    """`chunk_fn` of the points `bounds[0] <= p < bounds[1]` of the product grid of
    `shape`, made from its `axes` (named `names` in the grid's order, first axis slowest,
    as `grid_product` flattens them; JAX hands a `dict` over in sorted key order),
    padded to `padded` points by repeating the last one. Each device makes the indices of
    its own share (the sharding constraint) and gathers their values from the axes."""
    strides = [math.prod(shape[k + 1:]) for k in range(len(shape))]

    def block_fn(bounds, axes):
        s, e = bounds[0], bounds[1]
        idx = jnp.minimum(s + jnp.arange(padded, dtype=bounds.dtype), e - 1)
        idx = jax.lax.with_sharding_constraint(idx, sharding)
        points = {k: axes[k][(idx // stride) % n]
                  for k, stride, n in zip(names, strides, shape)}
        return chunk_fn(points)

    return block_fn


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


class _Devices:
    """The blocks of one sweep on the devices. `dispatch` starts a block, `collect` waits
    for it and copies its outputs into `results` (counting, per chunk, the points with
    non-finite outputs and with a non-zero status in `bad`). `fn` raising in either is
    entered in the manifest as the chunk's error and raised as a `RuntimeError`.

    **Arguments:**

    - `spec`: the `_SweepSpec`; `compiled`: `_compiled_chunk_fn` of it; `block`: the
      points per block (the compiled length).
    - `results`: the host arrays `(n_points, ...)` of every output, filled in place.
    - `pbar`: the progress bar, moved by every block collected.
    - `manifest`: the sweep's manifest (for a failed chunk's entry).
    """

    def __init__(self, spec, compiled, block, results, pbar, manifest):
        self.spec, self.compiled, self.block = spec, compiled, block
        self.results, self.pbar, self.manifest = results, pbar, manifest
        self.sharding = NamedSharding(spec.mesh, PartitionSpec(spec.mesh.axis_names))
        self.everywhere = NamedSharding(spec.mesh, PartitionSpec())
        # a product grid's axes, on every device once (the blocks' points are made there)
        self.axes = None if spec.axes is None else {
            k: self._everywhere(a) for k, a in spec.axes.items()}
        self.bad = {}  # chunk -> [points with non-finite outputs, with a non-zero status]

    def failed(self, i, e) -> NoReturn:
        manifest, n_points = self.manifest, self.spec.n_points
        start, stop = (_chunk_bounds(i, manifest["chunk_size"], n_points)
                       if manifest["chunk_size"] else (0, n_points))
        manifest["chunks"][str(i)] = {
            "status": "error", "start": start, "stop": stop, "error": repr(e)[:2000]
        }
        raise RuntimeError(
            f"`run_sweep`: `fn` failed on chunk {i} (points {start} to {stop - 1}). "
            "A failing point must not raise inside `fn`: return NaN or a non-zero "
            "`status` instead (e.g. `simulate(..., throw=False)`). Finished chunks "
            f"are kept in {self.spec.out_dir!r}; fix `fn` and run again to resume."
        ) from e

    def _everywhere(self, a: np.ndarray) -> jax.Array:
        """`a` on every device of the mesh (each process supplies its own devices')."""
        return jax.make_array_from_callback(a.shape, self.everywhere, lambda sl: a[sl])

    def dispatch(self, i, s, e):
        """Start points [s, e) of chunk i on the devices (asynchronously); returns the
        sharding of the block's points and the (pending) outputs."""
        if self.axes is not None:
            bounds = self._everywhere(np.asarray([s, e], dtype=_index_dtype()))
            try:
                return self.sharding, self.compiled(bounds, self.axes)
            except Exception as err:
                self.failed(i, err)
        block, host_grid = self.block, self.spec.host_grid
        if e - s == block:  # views of the grid, no copy
            cols = {k: v[s:e] for k, v in host_grid.items()}
        else:  # pad by repeating the last point: real, finite inputs, discarded
            idx = np.minimum(np.arange(s, s + block), e - 1)
            cols = {k: v[idx] for k, v in host_grid.items()}
        # Every process holds the whole grid; the callback is asked only for the slices
        # of this process's own devices.
        inputs = {
            k: jax.make_array_from_callback((block,), self.sharding, lambda sl, c=c: c[sl])
            for k, c in cols.items()
        }
        try:
            return self.sharding, self.compiled(inputs)
        except Exception as err:
            self.failed(i, err)

    def collect(self, i, s, e, out):
        """Wait for a block; copy its outputs (padding removed) into `results`."""
        leaves = jtu.tree_leaves(out)
        try:
            if jax.process_count() > 1:
                host = multihost_utils.process_allgather(leaves, tiled=True)
            else:
                host = jax.device_get(leaves)
        except Exception as err:
            self.failed(i, err)
        results = self.results
        for res, h in zip(results, host):
            res[s:e] = np.asarray(h)[: e - s]
        self.pbar.update(e - s)  # the bar moves with every block
        # counted now, while the devices compute the next block
        n_nonfinite, n_failed = _count_bad([r[s:e] for r in results], self.spec.status_leaves,
                                           e - s)
        counts = self.bad.setdefault(i, [0, None if n_failed is None else 0])
        counts[0] += n_nonfinite
        if n_failed is not None:
            counts[1] += n_failed
        return leaves
