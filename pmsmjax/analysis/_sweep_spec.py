"""What a sweep is, fixed before anything runs ([`run_sweep`][]): the checked grid and
options, `fn` traced once on abstract scalars (the structure of its outputs, their names
in the files, its `status` outputs), and the fingerprint that identifies the sweep in
`out_dir` (hashes of the grid, the chunk size, the output structure, the metadata and
`fn`'s jaxpr), so that resuming a sweep that changed in any of them is refused."""

from __future__ import annotations

import collections
import dataclasses
import hashlib
import json
import math
import os
import re
from collections.abc import Callable
from typing import Any

import jax
import jax.tree_util as jtu
import numpy as np
from jax.sharding import Mesh

from ._sweep_grid import SweepGrid, _canonical_metadata, _validate_grid


# Product grids up to this many points are made on the devices from their axes with
# 32-bit point indices where JAX has no 64-bit integers (float64 off); larger ones are
# then sent to the devices point by point.
_MAX_INDEXED_POINTS = 2**31 - 2**24
# Hashes of the printed jaxprs kept (`_hash_jaxpr`), as many as compiled sweep functions
# (`pmsmjax.analysis._sweep_devices`).
_JAXPR_CACHE_SIZE = 8


@dataclasses.dataclass(frozen=True)
class _SweepSpec:
    """One sweep as [`run_sweep`][] was asked for it (`_sweep_spec`).

    - `fn`, `closed_jaxpr`: the per-point function, and its trace on one abstract point.
    - `host_grid`: the checked grid, a `dict` of 1-D NumPy arrays of length `n_points`;
      `shape`: the grid shape of a `SweepGrid`, else None.
    - `axes`: for a product of axes (`SweepGrid.product_axes`), the checked axes, from
      which the devices make each block's points themselves; else None (the points are
      sent to the devices block by block).
    - `out_names`, `out_specs`, `out_treedef`: the outputs' names in the files, their
      per-point shapes and dtypes, and the PyTree structure that `fn` returns;
      `status_leaves`: the indices of the integer `status` outputs.
    - `parts`, `fingerprint`: the hashes that identify the sweep, and the hash of them.
    - `metadata_json`: the user metadata as canonical JSON.
    - `auto`: the automatic chunk size (`chunk_size=None`); `chunk_size`, `batch_size`,
      `keep_chunks`, `keep_result`, `mesh`, `out_dir`: the options, checked.
    - `is_writer`: this is process 0, which writes the files.
    """

    fn: Callable
    closed_jaxpr: Any
    host_grid: dict[str, np.ndarray]
    shape: tuple[int, ...] | None
    axes: dict[str, np.ndarray] | None
    n_points: int
    out_names: list[str]
    out_specs: list[jax.ShapeDtypeStruct]
    out_treedef: Any
    status_leaves: list[int]
    parts: dict[str, str]
    fingerprint: str
    metadata_json: str
    auto: bool
    chunk_size: int | None
    batch_size: int | None
    keep_chunks: bool
    keep_result: bool
    mesh: Mesh
    out_dir: str
    is_writer: bool

    @property
    def out_bytes(self) -> int:
        """Bytes of outputs per point."""
        return sum(int(np.prod(s.shape)) * np.dtype(s.dtype).itemsize for s in self.out_specs)


def _sweep_spec(fn, grid, *, out_dir, chunk_size, batch_size, metadata, mesh, dtype,
                allow_nonfinite, keep_chunks, keep_result=True) -> _SweepSpec:
    """[`run_sweep`][]'s arguments checked, and `fn` traced: the `_SweepSpec`."""
    if not callable(fn):
        raise TypeError(f"`run_sweep(fn=...)` must be callable; got {type(fn).__name__}.")
    shape = grid.shape if isinstance(grid, SweepGrid) else None
    product = grid.product_axes() if isinstance(grid, SweepGrid) else None
    if product is None:
        axes = None
        host_grid, n_points = _validate_grid(grid, dtype=dtype,
                                             allow_nonfinite=allow_nonfinite)
    else:
        # the points are the product of the axes: the axes are checked and converted (a
        # 2001 x 2001 grid: 4,002 values instead of 8 M), the points take their dtypes
        axes = {k: _validate_grid({k: a}, dtype=dtype, allow_nonfinite=allow_nonfinite)[0][k]
                for k, a in product.items()}
        host_grid = {k: np.ascontiguousarray(grid[k], dtype=axes[k].dtype) for k in grid}
        n_points = math.prod(shape)
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
        "grid": _hash_grid(host_grid, shape, axes),
        # the automatic size is chosen once and kept in the manifest and the chunk files
        "chunk_size": "auto" if auto else str(chunk_size),
        "outputs": _hash_text(
            json.dumps([[n, str(s.dtype), list(s.shape)] for n, s in zip(out_names, out_specs)])
        ),
        "metadata": _hash_text(metadata_json),
        "fn": _hash_jaxpr(closed_jaxpr),
    }
    fingerprint = _hash_text(json.dumps(parts, sort_keys=True))
    return _SweepSpec(
        fn=fn, closed_jaxpr=closed_jaxpr, host_grid=host_grid, shape=shape,
        axes=axes if axes is None or n_points <= _MAX_INDEXED_POINTS
        or jax.config.jax_enable_x64 else None,  # 32-bit indices would overflow
        n_points=n_points, out_names=out_names, out_specs=out_specs, out_treedef=out_treedef,
        status_leaves=status_leaves, parts=parts, fingerprint=fingerprint,
        metadata_json=metadata_json, auto=auto, chunk_size=chunk_size, batch_size=batch_size,
        keep_chunks=keep_chunks, keep_result=bool(keep_result), mesh=mesh, out_dir=out_dir,
        is_writer=is_writer)


# --------------------------------------------------------------------------------------
# Fingerprints


def _hash_text(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def _hash_grid(host_grid, shape, axes=None) -> str:
    """The grid's fingerprint: of its points, or of its axes for a product of them
    (`SweepGrid.product_axes`, converted as the points were; the points are then that
    product: a 2001 x 2001 x 1 grid hashes 16 kB instead of 96 MB)."""
    h = hashlib.sha256()
    h.update(json.dumps(list(shape) if shape is not None else None).encode())
    arrays = host_grid
    if axes is not None:
        h.update(b"product of axes")
        arrays = axes
    for key in sorted(arrays):
        a = arrays[key]
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
        while len(_JAXPR_TEXT_HASH) > _JAXPR_CACHE_SIZE:
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
    def per_point(flags):  # (n, ...) -> (n,): any flag of the point (one per point: as is)
        return flags if flags.ndim == 1 else flags.reshape(n, -1).any(axis=1)

    nonfinite = np.zeros(n, dtype=bool)
    for a in arrays:
        if np.issubdtype(a.dtype, np.inexact):
            nonfinite |= per_point(~np.isfinite(a))
    if not status_leaves:
        return int(np.count_nonzero(nonfinite)), None
    failed = np.zeros(n, dtype=bool)
    for i in status_leaves:
        failed |= per_point(arrays[i] != 0)
    return int(np.count_nonzero(nonfinite)), int(np.count_nonzero(failed))


def _output_tree(results, shape, out_treedef):
    if shape is not None:
        results = [r.reshape(*shape, *r.shape[1:]) for r in results]
    return jtu.tree_unflatten(out_treedef, results)

