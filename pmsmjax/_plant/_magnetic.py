r"""Magnetic models of the machine: the stator flux linkage as a function of the current.

A constant-inductance machine has $\psi_{dq} = [\psi_f + L_d i_d,\; L_q i_q]$. A saturated
one has $\psi_{dq} = \psi_{dq}(i_{dq})$, with cross-saturation (each flux depends on both
currents) and a PM flux that drops under load. Two sources are provided, both
`AbstractMagneticModel`s:

- `FluxMap`: a table `psi_d(i_d, i_q)`, `psi_q(i_d, i_q)` on a rectangular current grid
  (from a finite-element tool or a measurement), interpolated by a tensor-product
  not-a-knot C2 cubic spline (fourth-order accurate, twice differentiable, so gradients
  flow through it for tuning and identification). Outside the grid the flux is
  extended linearly with the incremental inductance of the nearest grid point (the
  saturated slope carries on).
- `AlgebraicSaturation`: the algebraic saturation model of Hinkkanen et al. (2017),
  written in its natural inverse form $i_{dq}(\psi_{dq})$ from a magnetic energy, with the
  magnet as a constant equivalent d-axis current $i_f$.

The plant keeps the stator *current* as its state and integrates
$L_{inc}(i)\,\frac{di}{dt} = u - R_s i - \omega J \psi(i) - \omega\,\partial\psi_h/\partial\theta$,
with the incremental inductance $L_{inc} = \partial\psi/\partial i$ (a 2 x 2 matrix): the
chain rule of $d\psi/dt = u - R_s i - \omega J \psi$, so it is the flux-linkage model
itself, written in the coordinates every other part of pmsmjax already uses (the
recording format, the controllers and observers measure currents, and the constant model
is its exact special case). The price is one 2 x 2 solve per evaluation; $L_{inc}$ is
positive definite for every physical map (each flux increases with its own current; a map
checked by `check_flux_map`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._sim._batching import by_batch


def solve2(a, b, c, d, r0, r1):
    """Solve `[[a, b], [c, d]] x = [r0, r1]` (element-wise, by Cramer's rule)."""
    det = a * d - b * c
    return (d * r0 - b * r1) / det, (a * r1 - c * r0) / det


def apparent_model(model, magnetic: AbstractMagneticModel, i_dq):
    """The constant machine model `model` (any module with `L_d`, `L_q` (H) and `psi_f`
    (V s) fields: `PMSMParams`, an observer's machine model) with those three replaced by
    the apparent values of `magnetic` at the current `i_dq` (A, `(2,)`): the constant
    machine whose flux equals `magnetic`'s at that current. A `magnetic` field of `model`
    itself is dropped (set to None), so the result is a constant-inductance machine. The
    one construction behind `observer.scheduled_at` and `analysis.apparent_plant`."""
    L_d, L_q, psi_f = magnetic.apparent_inductance(jnp.asarray(i_dq))
    out = eqx.tree_at(lambda m: (m.L_d, m.L_q, m.psi_f), model, (L_d, L_q, psi_f))
    if getattr(out, "magnetic", None) is not None:
        out = eqx.tree_at(lambda m: m.magnetic, out, None)
    return out


class AbstractMagneticModel(eqx.Module):
    r"""A machine's stator flux linkage $\psi_{dq}(i_{dq})$ in rotor coordinates.

    Concrete models implement `flux_and_inductance(i_d, i_q)` on components (A) and
    return `(psi_d, psi_q, L_dd, L_dq, L_qd, L_qq)`: the flux linkage (V s) and the
    incremental inductances $L_{xy} = \partial\psi_x / \partial i_y$ (H).
    """

    def flux_and_inductance(self, i_d, i_q):
        raise NotImplementedError  # pragma: no cover

    # -- public helpers on stacked vectors -------------------------------------------------
    def flux_dq(self, i_dq):
        """Stator flux linkage psi_dq (V s, (..., 2)) at the current `i_dq` (A, (..., 2))."""
        i_dq = jnp.asarray(i_dq)
        psi_d, psi_q, *_ = self.flux_and_inductance(i_dq[..., 0], i_dq[..., 1])
        return jnp.stack([psi_d, psi_q], -1)

    def incremental_inductance(self, i_dq):
        r"""Incremental inductance matrix $\partial\psi_{dq}/\partial i_{dq}$ (H, (..., 2, 2))
        at the current `i_dq` (A, (..., 2)): what the current's dynamics see."""
        i_dq = jnp.asarray(i_dq)
        _, _, l_dd, l_dq, l_qd, l_qq = self.flux_and_inductance(i_dq[..., 0], i_dq[..., 1])
        return jnp.stack([jnp.stack([l_dd, l_dq], -1), jnp.stack([l_qd, l_qq], -1)], -2)

    def apparent_inductance(self, i_dq):
        r"""Apparent (secant) model at the current `i_dq` (A, (..., 2)): `(L_d, L_q, psi_f)`
        (H, H, V s) such that $\psi_{dq}(i) = [\psi_f + L_d i_d,\; L_q i_q]$ exactly at
        this current, with $\psi_f = \psi_d(0, i_q)$ the PM flux under the present
        q-current (it drops with cross-saturation), $L_d = (\psi_d(i) - \psi_f)/i_d$ and
        $L_q = (\psi_q(i) - \psi_q(i_d, 0))/i_q$. At $i_d = 0$ (or $i_q = 0$) the secant is
        replaced by its limit, the incremental inductance there."""
        i_dq = jnp.asarray(i_dq)
        i_d, i_q = i_dq[..., 0], i_dq[..., 1]
        zero = jnp.zeros_like(i_d)
        psi_d, psi_q, l_dd, _, _, l_qq = self.flux_and_inductance(i_d, i_q)
        psi_f, _, l_dd0, *_ = self.flux_and_inductance(zero, i_q)
        _, psi_q0, _, _, _, l_qq0 = self.flux_and_inductance(i_d, zero)
        L_d = _secant(psi_d - psi_f, i_d, 0.5 * (l_dd + l_dd0))
        L_q = _secant(psi_q - psi_q0, i_q, 0.5 * (l_qq + l_qq0))
        return L_d, L_q, psi_f

    def reciprocity_error(self, i_dq):
        r"""Relative asymmetry $|L_{dq} - L_{qd}| / \sqrt{L_{dd} L_{qq}}$ (-) at `i_dq` (A).

        Zero for every map derived from a magnetic energy (a lossless magnetic field);
        a measured or computed map departs from it by its errors."""
        i_dq = jnp.asarray(i_dq)
        _, _, l_dd, l_dq, l_qd, l_qq = self.flux_and_inductance(i_dq[..., 0], i_dq[..., 1])
        return jnp.abs(l_dq - l_qd) / jnp.sqrt(jnp.abs(l_dd * l_qq))

    def torque(self, i_dq, n_p):
        r"""Electromagnetic torque $\tfrac32 n_p\,\psi \times i$ (N m) at `i_dq` (A) for a
        three-phase machine with `n_p` pole pairs."""
        i_dq = jnp.asarray(i_dq)
        psi = self.flux_dq(i_dq)
        return 1.5 * n_p * (psi[..., 0] * i_dq[..., 1] - psi[..., 1] * i_dq[..., 0])

    def sample(self, i_d, i_q) -> FluxMap:
        """This model tabulated on the grid `i_d` x `i_q` (A, 1-D, increasing): a `FluxMap`
        (what a finite-element tool or a measurement would deliver)."""
        dd, qq = np.meshgrid(np.asarray(i_d, float), np.asarray(i_q, float), indexing="ij")
        psi = np.asarray(self.flux_dq(jnp.stack([dd, qq], -1)))
        return FluxMap(i_d, i_q, psi[..., 0], psi[..., 1])


def _secant(dpsi, di, limit):
    small = jnp.abs(di) < 1e-9
    return jnp.where(small, limit, dpsi / jnp.where(small, 1.0, di))


class FluxMap(AbstractMagneticModel):
    r"""Tabulated flux map: $\psi_d$, $\psi_q$ (V s) on a rectangular grid of `i_d` x `i_q` (A).

    Interpolated by a tensor-product not-a-knot C2 cubic spline (error $O(h^4)$ in the
    flux, $O(h^3)$ in the inductances); extended linearly outside the grid with the
    incremental inductances of the nearest grid point. Files: `read_flux_map` (CSV with
    the header `i_d,i_q,psi_d,psi_q`, any row order, or an NPZ with the same arrays).

    **Arguments:**

    - `i_d`: d-axis grid currents (A, 1-D, strictly increasing, at least 4 points).
    - `i_q`: q-axis grid currents (A, 1-D, strictly increasing, at least 4 points).
    - `psi_d`, `psi_q`: flux linkages (V s, shape `(len(i_d), len(i_q))`).
    """

    i_d: jax.Array
    i_q: jax.Array
    psi_d: jax.Array
    psi_q: jax.Array
    _cells: jax.Array  # (n_d - 1, n_q - 1, 2, 4, 4) polynomial coefficients per cell
    _table: jax.Array  # (n_d - 1, n_q - 1, 6, 16) the same with derivatives (_product_table)
    # per axis: equally spaced (a cell found by one division instead of a search)
    _uniform: tuple = eqx.field(static=True, default=(False, False))

    def __init__(self, i_d, i_q, psi_d, psi_q):
        i_d, i_q = jnp.asarray(i_d, float), jnp.asarray(i_q, float)
        psi_d, psi_q = jnp.asarray(psi_d, float), jnp.asarray(psi_q, float)
        for name, axis in (("i_d", i_d), ("i_q", i_q)):
            if axis.ndim != 1 or axis.shape[0] < 4:
                raise ValueError(
                    f"`FluxMap({name}=...)` (A) must be a 1-D grid of at least 4 currents "
                    f"(a cubic spline needs 4 per axis); got shape {axis.shape}.")
        shape = (i_d.shape[0], i_q.shape[0])
        for name, table in (("psi_d", psi_d), ("psi_q", psi_q)):
            if table.shape != shape:
                raise ValueError(
                    f"`FluxMap({name}=...)` (V s) must have shape (len(i_d), len(i_q)) = "
                    f"{shape}; got {table.shape}.")
        uniform = (False, False)
        if all(isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer)
               for x in (i_d, i_q)):
            for name, axis in (("i_d", i_d), ("i_q", i_q)):
                if not bool(jnp.all(jnp.diff(axis) > 0)):
                    raise ValueError(
                        f"`FluxMap({name}=...)` (A) must be strictly increasing (a grid "
                        f"without duplicates); got {np.asarray(axis)}.")
            uniform = tuple(bool(np.allclose(np.diff(np.asarray(a)), float(a[1] - a[0]),
                                             rtol=1e-9, atol=0.0)) for a in (i_d, i_q))
        self._uniform = uniform
        self.i_d, self.i_q, self.psi_d, self.psi_q = i_d, i_q, psi_d, psi_q
        cells = _bicubic_cells(i_d, i_q, jnp.stack([psi_d, psi_q], -1))
        xp = np if isinstance(cells, np.ndarray) else jnp
        self._cells, self._table = jnp.asarray(cells), jnp.asarray(_product_table(cells, xp))

    def flux_and_inductance(self, i_d, i_q):
        lo_d, hi_d, lo_q, hi_q = self.i_d[0], self.i_d[-1], self.i_q[0], self.i_q[-1]
        d, q = jnp.clip(i_d, lo_d, hi_d), jnp.clip(i_q, lo_q, hi_q)
        kd, t, hd = _locate(self.i_d, d, self._uniform[0])
        kq, u, hq = _locate(self.i_q, q, self._uniform[1])
        f_d, f_q, fx_d, fy_d, fx_q, fy_q = _cell_values(self._cells, self._table, kd, kq,
                                                        t, u, hd, hq)
        dd, dq = i_d - d, i_q - q  # linear extension outside the grid
        psi_d = f_d + fx_d * dd + fy_d * dq
        psi_q = f_q + fx_q * dd + fy_q * dq
        return psi_d, psi_q, fx_d, fy_d, fx_q, fy_q


def _cell_horner(cells, table, kd, kq, t, u, hd, hq):
    """`(psi_d, psi_q, dpsi_d/di_d, dpsi_d/di_q, dpsi_q/di_d, dpsi_q/di_q)` of the cell
    `(kd, kq)` at its local coordinates `(t, u)` (cell widths `hd`, `hq`): Horner's scheme
    on the cell's coefficients, written out element-wise. XLA fuses it into one loop over
    a batch; small einsums became dot products that cost four times as much there."""
    c = cells[kd, kq]  # (..., 2, 4, 4): psi_x = sum_ij c[x, i, j] t^i u^j
    out = []
    for x in (0, 1):
        cx = [[c[..., x, i, j] for j in range(4)] for i in range(4)]
        cu = [((cx[i][3] * u + cx[i][2]) * u + cx[i][1]) * u + cx[i][0] for i in range(4)]
        du = [(3.0 * cx[i][3] * u + 2.0 * cx[i][2]) * u + cx[i][1] for i in range(4)]
        out.append((((cu[3] * t + cu[2]) * t + cu[1]) * t + cu[0],
                    ((3.0 * cu[3] * t + 2.0 * cu[2]) * t + cu[1]) / hd,
                    (((du[3] * t + du[2]) * t + du[1]) * t + du[0]) / hq))
    (f_d, fx_d, fy_d), (f_q, fx_q, fy_q) = out
    return f_d, f_q, fx_d, fy_d, fx_q, fy_q


def _cell_product(cells, table, kd, kq, t, u, hd, hq):
    """`_cell_horner` as one product of the cell's `(6, 16)` table (`_product_table`)
    with the monomials t^i u^j: a single run's step is 1.5 times as fast with it (XLA
    CPU, BENCHMARKS.md), a batch of 64 three times as slow."""
    tp = jnp.stack([jnp.ones_like(t), t, t * t, t * t * t], -1)
    up = jnp.stack([jnp.ones_like(u), u, u * u, u * u * u], -1)
    basis = (tp[..., :, None] * up[..., None, :]).reshape(jnp.shape(t) + (16,))
    o = jnp.sum(table[kd, kq] * basis[..., None, :], -1)
    return o[..., 0], o[..., 1], o[..., 2] / hd, o[..., 3] / hq, o[..., 4] / hd, o[..., 5] / hq


def _cell_many(axis_size, in_batched, *a):
    return jax.vmap(_cell_horner, in_axes=[0 if b else None for b in in_batched])(*a)


#: A cell's values: the table product for a single run (and a batch of one), Horner's
#: scheme for a batch; derivatives through Horner's scheme (`by_batch`).
_cell_values = by_batch(_cell_product, _cell_many, _cell_horner)


def _product_table(cells, xp):
    """`(..., 6, 16)`: the coefficients of `(psi_d, psi_q, h_d dpsi_d/di_d, h_q
    dpsi_d/di_q, h_d dpsi_q/di_d, h_q dpsi_q/di_q)` on the monomials t^i u^j (index 4 i +
    j) of the per-cell coefficients `cells` `(..., 2, 4, 4)` (`_bicubic_cells`)."""
    k = xp.asarray([1.0, 2.0, 3.0], dtype=cells.dtype)
    rows = []
    for x in (0, 1):
        c = cells[..., x, :, :]
        d_t = xp.concatenate([c[..., 1:, :] * k[:, None], xp.zeros_like(c[..., :1, :])], -2)
        d_u = xp.concatenate([c[..., :, 1:] * k, xp.zeros_like(c[..., :, :1])], -1)
        rows.append((c, d_t, d_u))
    (vd, td, ud), (vq, tq, uq) = rows
    return xp.stack([vd, vq, td, ud, tq, uq], -3).reshape(cells.shape[:-3] + (6, 16))


def _locate(grid, x, uniform=False):
    """Cell index `k`, local coordinate `t` in [0, 1] and cell width `h` of `x` in `grid`
    (`uniform`: the grid is equally spaced, so the cell is found by one division; the
    spline is C2, so a rounding across a knot changes nothing but the last digits)."""
    if uniform:
        n = grid.shape[0] - 1
        h = (grid[-1] - grid[0]) / n
        s = (x - grid[0]) / h
        k = jnp.clip(jnp.floor(s), 0, n - 1)
        return k.astype(jnp.int32), s - k, h + 0.0 * s
    k = jnp.clip(jnp.searchsorted(grid, x, side="right", method="compare_all") - 1,
                 0, grid.shape[0] - 2)
    h = grid[k + 1] - grid[k]
    return k, (x - grid[k]) / h, h


#: Bicubic Hermite basis on [0, 1]: coefficients of t^0..t^3 of the four functions that
#: carry f(0), f(1), h f'(0), h f'(1).
_HERMITE = np.array([[1.0, 0.0, -3.0, 2.0],
                     [0.0, 0.0, 3.0, -2.0],
                     [0.0, 1.0, -2.0, 1.0],
                     [0.0, 0.0, -1.0, 1.0]])


def _spline_slopes(x, f, xp):
    """Knot slopes of the not-a-knot C2 cubic spline through `f` (n, ...) at the knots `x`
    (n,), along axis 0 (the conditions of de Boor's "A Practical Guide to Splines", ch.
    IV, as SciPy's `CubicSpline(bc_type="not-a-knot")` uses them; tested against it).
    `xp` is numpy (a map from a file: no compilation) or jax.numpy (a traced map)."""
    n = x.shape[0]
    h = xp.diff(x)
    d = (f[1:] - f[:-1]) / h.reshape((-1,) + (1,) * (f.ndim - 1))
    A = xp.zeros((n, n), dtype=f.dtype)
    rows = xp.arange(1, n - 1)
    hh = h.reshape((-1,) + (1,) * (f.ndim - 1))
    interior = 3.0 * (hh[1:] * d[:-1] + hh[:-1] * d[1:])
    if xp is np:
        A[rows, rows - 1] = h[1:]
        A[rows, rows] = 2.0 * (h[:-1] + h[1:])
        A[rows, rows + 1] = h[:-1]
        A[0, 0], A[0, 1] = h[1], h[0] + h[1]
        A[-1, -2], A[-1, -1] = h[-1] + h[-2], h[-2]
    else:
        A = A.at[rows, rows - 1].set(h[1:]).at[rows, rows].set(2.0 * (h[:-1] + h[1:]))
        A = A.at[rows, rows + 1].set(h[:-1])
        A = A.at[0, 0].set(h[1]).at[0, 1].set(h[0] + h[1])
        A = A.at[-1, -2].set(h[-1] + h[-2]).at[-1, -1].set(h[-2])
    first = ((h[0] + 2.0 * (h[0] + h[1])) * h[1] * d[0] + h[0] ** 2 * d[1]) / (h[0] + h[1])
    last = (h[-1] ** 2 * d[-2] + (2.0 * (h[-2] + h[-1]) + h[-1]) * h[-2] * d[-1]) \
        / (h[-2] + h[-1])
    rhs = xp.concatenate([first[None], interior, last[None]], 0)
    flat = rhs.reshape(n, -1)
    return xp.linalg.solve(A, flat).reshape(f.shape)


def _bicubic_cells(x, y, f):
    """Per-cell polynomial coefficients `(nx-1, ny-1, m, 4, 4)` of the tensor-product
    not-a-knot C2 cubic spline through `f` `(nx, ny, m)` on the grid `x` x `y`.

    The node derivatives f_x, f_y, f_xy come from the spline conditions along each axis
    (`_spline_slopes`); on each cell the spline is the bicubic Hermite polynomial of those
    node values, stored so that an evaluation is one gather and a few multiplications (a
    closed-loop step evaluates the map four times per sampling period). Written here
    rather than taken from an interpolation library because building such a spline there
    took seconds of compilation for every map, and a preset builds one each time it is
    loaded; the dense solves here take microseconds (numpy) for a map from a file."""
    concrete = not any(isinstance(v, jax.core.Tracer) for v in (x, y, f))
    xp = np if concrete else jnp
    x, y, f = (xp.asarray(v, dtype=float) if concrete else v for v in (x, y, f))
    fx = _spline_slopes(x, f, xp)
    fy = xp.moveaxis(_spline_slopes(y, xp.moveaxis(f, 1, 0), xp), 0, 1)
    fxy = xp.moveaxis(_spline_slopes(y, xp.moveaxis(fx, 1, 0), xp), 0, 1)
    hx, hy = xp.diff(x)[:, None, None], xp.diff(y)[None, :, None]

    def corners(g):  # (nx-1, ny-1, m, 2, 2): g at the cell's corners [a, b]
        return xp.stack([xp.stack([g[:-1, :-1], g[:-1, 1:]], -1),
                         xp.stack([g[1:, :-1], g[1:, 1:]], -1)], -2)

    # Hermite data G[a, b]: rows (f(0), f(1), h_x f_x(0), h_x f_x(1)) x columns likewise
    # in y, per output.
    G = xp.concatenate([
        xp.concatenate([corners(f), corners(fy) * hy[..., None, None]], -1),
        xp.concatenate([corners(fx) * hx[..., None, None],
                        corners(fxy) * (hx * hy)[..., None, None]], -1)], -2)
    # coefficient c_ij of t^i u^j = sum_ab H[a, i] G[a, b] H[b, j]
    return xp.einsum("ai,...ab,bj->...ij", _HERMITE, G, _HERMITE)


class AlgebraicSaturation(AbstractMagneticModel):
    r"""Algebraic saturation model with cross-saturation and a PM flux (SI units).

    The inverse model of M. Hinkkanen, P. Pescetto, E. Mölsä, S. E. Saarakkala,
    G. Pellegrino, R. Bojoi, "Sensorless self-commissioning of synchronous reluctance
    motors at standstill without rotor locking," IEEE Trans. Ind. Appl. 53(3),
    pp. 2120-2129, 2017, eqs. (5)-(6), with the magnet added as a constant equivalent
    d-axis current $i_f$ (a magnet is a constant MMF in the d-axis magnetic circuit):

    $$i_d = \Big(a_{d0} + a_{dd}|\psi_d|^S + \frac{a_{dq}}{V+2}|\psi_d|^U|\psi_q|^{V+2}\Big)
      \psi_d - i_f,\qquad
      i_q = \Big(a_{q0} + a_{qq}|\psi_q|^T + \frac{a_{dq}}{U+2}|\psi_d|^{U+2}|\psi_q|^V\Big)
      \psi_q.$$

    Both are the gradient of the magnetic energy
    $W(\psi) = \frac{a_{d0}}2\psi_d^2 + \frac{a_{dd}}{S+2}|\psi_d|^{S+2}
    + \frac{a_{q0}}2\psi_q^2 + \frac{a_{qq}}{T+2}|\psi_q|^{T+2}
    + \frac{a_{dq}}{(U+2)(V+2)}|\psi_d|^{U+2}|\psi_q|^{V+2} - i_f\psi_d$, so the model is
    reciprocal exactly. The energy is convex (the incremental inductance positive
    definite) where its quadratic terms dominate the cross-saturation term; outside that
    region the model has left the range it describes (`check_flux_map` on a sampled map
    finds it). `flux_and_inductance` inverts the model by continuation from zero flux
    (the target current moves from that of zero flux to the requested one over half of
    `newton_steps`, one Newton step each, then plain Newton steps): it follows the
    solution path and converges to the last digits wherever the path stays in that range
    (tested over three times the preset's current limit). Derivatives flow through the
    iterations.

    **Arguments** (SI; the $a$ are in A per (V s)$^{k+1}$ for the power $k$ they multiply):

    - `a_d0`, `a_q0`: unsaturated inverse inductances (1/H), > 0.
    - `a_dd`, `a_qq`: self-saturation coefficients (A/(V s)^(S+1), A/(V s)^(T+1)), >= 0.
    - `a_dq`: cross-saturation coefficient (A/(V s)^(U+V+3)), >= 0.
    - `S`, `T`, `U`, `V`: exponents (-, static), >= 0; defaults 5, 1, 1, 0 (the paper's
      SyRM). Even exponents make the model a polynomial in the flux (smooth
      everywhere); odd ones leave a kink in the inductance at zero flux.
    - `i_f`: equivalent magnet current (A), >= 0 (0: a synchronous reluctance machine).
    - `newton_steps`: iterations of the inversion (static), default 40.
    """

    a_d0: float
    a_dd: float
    a_q0: float
    a_qq: float
    a_dq: float
    i_f: float
    S: float = eqx.field(static=True, default=5.0)
    T: float = eqx.field(static=True, default=1.0)
    U: float = eqx.field(static=True, default=1.0)
    V: float = eqx.field(static=True, default=0.0)
    newton_steps: int = eqx.field(static=True, default=40)

    def __check_init__(self):
        from .._validate import check_positive
        for name in ("a_d0", "a_q0"):
            check_positive("AlgebraicSaturation", name, getattr(self, name), "1/H")
        for name in ("a_dd", "a_qq", "a_dq"):
            check_positive("AlgebraicSaturation", name, getattr(self, name), "SI",
                           allow_zero=True)
        check_positive("AlgebraicSaturation", "i_f", self.i_f, "A", allow_zero=True)
        for name in ("S", "T", "U", "V"):
            if not float(getattr(self, name)) >= 0.0:
                raise ValueError(f"`AlgebraicSaturation({name}=...)` must be >= 0; got "
                                 f"{getattr(self, name)!r}.")

    def current(self, psi_d, psi_q):
        """Current `(i_d, i_q)` (A) at the flux linkage `(psi_d, psi_q)` (V s): the model's
        explicit direction."""
        ad, aq = abs(psi_d), abs(psi_q)
        k_d = (self.a_d0 + self.a_dd * ad ** self.S
               + self.a_dq / (self.V + 2) * ad ** self.U * aq ** (self.V + 2))
        k_q = (self.a_q0 + self.a_qq * aq ** self.T
               + self.a_dq / (self.U + 2) * ad ** (self.U + 2) * aq ** self.V)
        return k_d * psi_d - self.i_f, k_q * psi_q

    def energy(self, psi_d, psi_q):
        """Magnetic energy W(psi) (J per unit of the amplitude-invariant scaling, i.e.
        A V s) whose gradient is `current`."""
        ad, aq = abs(psi_d), abs(psi_q)
        S, T, U, V = self.S, self.T, self.U, self.V
        return (0.5 * self.a_d0 * psi_d ** 2 + self.a_dd / (S + 2) * ad ** (S + 2)
                + 0.5 * self.a_q0 * psi_q ** 2 + self.a_qq / (T + 2) * aq ** (T + 2)
                + self.a_dq / ((U + 2) * (V + 2)) * ad ** (U + 2) * aq ** (V + 2)
                - self.i_f * psi_d)

    def _hessian(self, psi_d, psi_q):
        """d i / d psi (1/H) as (g_dd, g_dq, g_qq): the Hessian of the energy."""
        ad, aq = abs(psi_d), abs(psi_q)
        S, T, U, V = self.S, self.T, self.U, self.V
        g_dd = (self.a_d0 + (S + 1) * self.a_dd * ad ** S
                + self.a_dq * (U + 1) / (V + 2) * ad ** U * aq ** (V + 2))
        g_qq = (self.a_q0 + (T + 1) * self.a_qq * aq ** T
                + self.a_dq * (V + 1) / (U + 2) * ad ** (U + 2) * aq ** V)
        g_dq = self.a_dq * ad ** U * psi_d * aq ** V * psi_q
        return g_dd, g_dq, g_qq

    def flux_and_inductance(self, i_d, i_q):
        # Concrete inputs (sampling a map, a report) run in numpy: a Python loop of a few
        # dozen vector operations, where the compiled loop would first take seconds to build.
        concrete = not any(isinstance(v, jax.core.Tracer)
                           for v in jax.tree_util.tree_leaves((self, i_d, i_q)))
        xp = np if concrete else jnp
        i_d, i_q = xp.broadcast_arrays(xp.asarray(i_d, float), xp.asarray(i_q, float))
        n_path = self.newton_steps // 2

        def newton(k, psi):
            # Continuation: the target current moves from that of psi = 0, (-i_f, 0), to
            # (i_d, i_q) over the first half of the iterations (one Newton step each), so
            # the iterate follows the solution path from zero flux; the second half are
            # plain Newton steps on the final target (quadratic convergence).
            s = xp.minimum((k + 1) / n_path, 1.0)
            t_d, t_q = (1.0 - s) * -self.i_f + s * i_d, s * i_q
            psi_d, psi_q = psi
            r_d, r_q = self.current(psi_d, psi_q)
            g_dd, g_dq, g_qq = self._hessian(psi_d, psi_q)
            s_d, s_q = solve2(g_dd, g_dq, g_dq, g_qq, r_d - t_d, r_q - t_q)
            return psi_d - s_d, psi_q - s_q

        psi = (xp.zeros_like(i_d), xp.zeros_like(i_d))
        if concrete:
            for k in range(self.newton_steps):
                psi = newton(k, psi)
            psi_d, psi_q = psi
        else:
            psi_d, psi_q = jax.lax.fori_loop(0, self.newton_steps, newton, psi)
        g_dd, g_dq, g_qq = self._hessian(psi_d, psi_q)
        det = g_dd * g_qq - g_dq * g_dq
        return psi_d, psi_q, g_qq / det, -g_dq / det, -g_dq / det, g_dd / det


def constant_model(model: AbstractMagneticModel, how: str = "small-current", i_max=None):
    r"""The constant `(L_d, L_q, psi_f)` (H, H, V s) a drive would deploy for `model`.

    - `"small-current"` (the default): the incremental inductances and the PM flux at zero
      current, what a no-load back-EMF test and a small-signal (standstill injection)
      commissioning measure, and what most drives run with. Exact at no load, it is the
      model that drifts furthest from the machine as the load grows.
    - `"rated"`: the apparent (secant) inductances and PM flux at the current `i_max` (A)
      on the q axis, what a loaded test at rated current measures.
    - `"fit"`: the least-squares fit of $[\psi_f + L_d i_d,\; L_q i_q]$ to the model over a
      31 x 31 grid of currents inside the circle $|i| \le$ `i_max` (A) with $i_d \le 0$
      (the motoring and field-weakening region).
    """
    how_all = ("small-current", "rated", "fit")
    if how not in how_all:
        raise ValueError(f"`constant_model(how=...)` must be one of {how_all}; got {how!r}.")
    if how != "small-current" and (i_max is None or not float(i_max) > 0):
        raise ValueError(f"`constant_model(how={how!r})` needs the current limit `i_max` (A) "
                         f"> 0; got {i_max!r}.")
    if how == "small-current":
        psi_d, _, l_dd, _, _, l_qq = model.flux_and_inductance(jnp.zeros(()), jnp.zeros(()))
        return float(l_dd), float(l_qq), float(psi_d)
    if how == "rated":
        L_d, L_q, psi_f = model.apparent_inductance(jnp.asarray([0.0, float(i_max)]))
        return float(L_d), float(L_q), float(psi_f)
    g = np.linspace(-1.0, 1.0, 31) * float(i_max)
    dd, qq = np.meshgrid(g[g <= 0], g, indexing="ij")
    inside = dd ** 2 + qq ** 2 <= float(i_max) ** 2 + 1e-9
    i_d, i_q = dd[inside], qq[inside]
    psi = np.asarray(model.flux_dq(jnp.stack([i_d, i_q], -1)))
    (psi_f, L_d), *_ = np.linalg.lstsq(np.stack([np.ones_like(i_d), i_d], -1), psi[:, 0],
                                       rcond=None)
    L_q = float(np.dot(i_q, psi[:, 1]) / np.dot(i_q, i_q))
    return float(L_d), L_q, float(psi_f)
