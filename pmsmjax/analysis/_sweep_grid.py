"""The grid of a sweep ([`run_sweep`][]): Cartesian products of axes ([`grid_product`][],
a [`SweepGrid`][]), and the checks and conversions of a grid and of the sweep's metadata
before anything runs."""

from __future__ import annotations

import json
from collections.abc import Mapping

import jax
import numpy as np


class SweepGrid(dict):
    """A flattened Cartesian-product grid, made by [`grid_product`][].

    A plain `dict` mapping each axis name to a 1-D array of length
    `N = prod(shape)` (first axis slowest, like `np.meshgrid(..., indexing="ij")` flattened
    in C order), which also remembers:

    - `shape`: the grid shape, `tuple(len(a) for a in axes.values())`;
    - `axes`: the 1-D axis arrays it was built from.

    [`run_sweep`][] reshapes its outputs from `(N, ...)` to `(*shape, ...)` for such grids,
    and identifies the sweep by the axes rather than by every point (the arrays of a grid
    from `grid_product` are read-only; a grid whose arrays were replaced is identified by
    its points).

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
        self._made = None  # the arrays grid_product made (set there; see `product_axes`)

    def product_axes(self) -> dict[str, np.ndarray] | None:
        """The axes, if the grid still holds the read-only arrays `grid_product` made from
        them (then the points are their product); otherwise None."""
        made = getattr(self, "_made", None)
        if (made is None or set(made) != set(self) or set(self.axes) != set(self)
                or any(self[k] is not v or v.flags.writeable for k, v in made.items())
                or any(a.flags.writeable for a in self.axes.values())):
            return None
        return self.axes

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
        arrays[name] = np.array(a)  # a copy of its own (made read-only below)
    mesh = np.meshgrid(*arrays.values(), indexing="ij")
    points = {name: m.reshape(-1) for name, m in zip(arrays, mesh)}
    for a in (*arrays.values(), *mesh, *points.values()):
        a.flags.writeable = False  # the points stay the product of the axes
    grid = SweepGrid(points, shape=tuple(a.size for a in arrays.values()), axes=arrays)
    grid._made = dict(points)
    return grid


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
