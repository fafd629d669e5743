r"""Flux-map files (`read_flux_map`) and the check of a magnetic model (`check_flux_map`).

A flux map is the stator flux linkage of a machine tabulated on a rectangular grid of
currents, as a finite-element tool or a measurement delivers it:

- CSV: one row per grid point, the header naming the columns `i_d,i_q,psi_d,psi_q`
  (A, A, V s, V s; peak values of the amplitude-invariant dq transform, `psi_d` along
  the magnet), the rows in any order; blank lines and lines starting with `#` are
  skipped, other columns (a torque, say) are ignored.
- NPZ (`numpy.savez`): the same four 1-D arrays as the CSV columns, or the axes `i_d`
  `(n_d,)` and `i_q` `(n_q,)` (increasing) with the tables `psi_d` and `psi_q`
  `(n_d, n_q)`.

A file that is not a usable map raises `FluxMapError` (a `ValueError`) naming the file,
what is wrong, where (rows, grid points) and what is allowed.
"""

from __future__ import annotations

import dataclasses
import math
import os

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._magnetic import AbstractMagneticModel, FluxMap


COLUMNS = ("i_d", "i_q", "psi_d", "psi_q")
_UNITS = {"i_d": "A", "i_q": "A", "psi_d": "V s", "psi_q": "V s"}
#: Relative reciprocity asymmetry above which `check_flux_map` warns.
RECIPROCITY_TOL = 0.05
_SHOW = 5  # how many offending rows / points an error lists


class FluxMapError(ValueError):
    """A flux-map file that is not a usable map: the message names the file, what is
    wrong, where (rows or grid points) and what is allowed."""


def _list(items, n=_SHOW) -> str:
    items = list(items)
    more = f" and {len(items) - n} more" if len(items) > n else ""
    return ", ".join(items[:n]) + more


def _pt(i_d, i_q) -> str:
    return f"(i_d, i_q) = ({i_d:.6g}, {i_q:.6g}) A"


class _Map:
    def __init__(self, source: str):
        self.source = source

    def fail(self, msg: str):
        raise FluxMapError(f"flux map {self.source}: {msg}")

    # -- CSV -------------------------------------------------------------------------------
    def csv_columns(self, text: str):
        rows, header, names = [], None, None
        for n, line in enumerate(text.splitlines(), 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            fields = [f.strip().strip('"').strip("'").strip() for f in s.split(",")]
            if header is None:
                header, names = n, fields
                missing = [c for c in COLUMNS if c not in names]
                if missing:
                    self.fail(f"missing column{'s' if len(missing) > 1 else ''} "
                              f"{', '.join(missing)} in the header (line {n}: {s!r}); a "
                              f"flux-map CSV has the comma-separated header "
                              f"{','.join(COLUMNS)} (A, A, V s, V s), other columns ignored")
                dup = sorted({c for c in COLUMNS if names.count(c) > 1})
                if dup:
                    self.fail(f"column {', '.join(dup)} appears twice in the header "
                              f"(line {n}); each of {','.join(COLUMNS)} must appear once")
                continue
            if len(fields) != len(names):
                self.fail(f"line {n} has {len(fields)} fields, the header (line {header}) "
                          f"{len(names)}; every row must have one value per column")
            vals = []
            for c in COLUMNS:
                v = fields[names.index(c)]
                try:
                    vals.append(float(v))
                except ValueError:
                    self.fail(f"line {n}: {c} = {v!r} is not a number ({_UNITS[c]}); "
                              "every value must be a decimal number")
            rows.append((n, vals))
        if header is None:
            self.fail(f"no header: the file is empty; a flux-map CSV starts with the header "
                      f"{','.join(COLUMNS)}")
        if not rows:
            self.fail("no data rows after the header; one row per grid point is needed")
        lines = [f"line {n}" for n, _ in rows]
        data = np.array([v for _, v in rows], float)
        return lines, data.T

    # -- columns -> tables ------------------------------------------------------------------
    def from_columns(self, where: list[str], cols):
        i_d, i_q, psi_d, psi_q = (np.asarray(c, float) for c in cols)
        bad = ~np.isfinite(np.stack([i_d, i_q, psi_d, psi_q]))
        if bad.any():
            rows = np.flatnonzero(bad.any(0))
            self.fail(f"non-finite values (NaN or inf) in {_list(where[k] for k in rows)} "
                      f"(columns {', '.join(c for c, b in zip(COLUMNS, bad.any(1)) if b)}); "
                      "every value must be a finite number")
        ax_d, k_d = _axis(i_d)
        ax_q, k_q = _axis(i_q)
        n_d, n_q = len(ax_d), len(ax_q)
        flat = k_d * n_q + k_q
        order = np.argsort(flat, kind="stable")
        s = flat[order]
        dup = np.flatnonzero(s[1:] == s[:-1])
        if dup.size:
            pts = []
            for j in dup:
                a, b = order[j], order[j + 1]
                pts.append(f"{_pt(i_d[a], i_q[a])} in {where[a]} and {where[b]}")
            self.fail(f"duplicate grid points: {_list(pts)}; each (i_d, i_q) point must "
                      "appear once")
        if len(flat) != n_d * n_q:
            have = np.zeros(n_d * n_q, bool)
            have[flat] = True
            miss = [_pt(ax_d[k // n_q], ax_q[k % n_q]) for k in np.flatnonzero(~have)]
            self.fail(f"not a rectangular grid: {len(flat)} points on {n_d} i_d values x "
                      f"{n_q} i_q values, missing {_list(miss)}; the map must hold every "
                      "combination of its i_d and i_q values")
        tab_d = np.empty(n_d * n_q)
        tab_q = np.empty(n_d * n_q)
        tab_d[flat], tab_q[flat] = psi_d, psi_q
        return ax_d, ax_q, tab_d.reshape(n_d, n_q), tab_q.reshape(n_d, n_q)

    def from_tables(self, i_d, i_q, psi_d, psi_q) -> FluxMap:
        for name, ax in (("i_d", i_d), ("i_q", i_q)):
            if ax.ndim != 1 or ax.size < 4:
                self.fail(f"{name} has {ax.size} grid values (shape {ax.shape}); the "
                          "interpolating spline needs at least 4 per axis")
            if not np.all(np.isfinite(ax)) or not np.all(np.diff(ax) > 0):
                self.fail(f"the axis {name} must be finite and strictly increasing; got "
                          f"{np.array2string(ax, threshold=8)} A")
        for name, tab in (("psi_d", psi_d), ("psi_q", psi_q)):
            if tab.shape != (i_d.size, i_q.size):
                self.fail(f"{name} has shape {tab.shape}; it must be (len(i_d), len(i_q)) "
                          f"= {(i_d.size, i_q.size)}")
            bad = np.argwhere(~np.isfinite(tab))
            if bad.size:
                self.fail(f"non-finite values (NaN or inf) in {name} at "
                          f"{_list(_pt(i_d[a], i_q[b]) for a, b in bad)}; every value must "
                          "be a finite number")
        for msg in _table_errors(i_d, i_q, psi_d, psi_q):
            self.fail(msg)
        fm = FluxMap(i_d, i_q, psi_d, psi_q)
        for msg in _inductance_errors(fm):
            self.fail(msg)
        return fm


def _axis(x):
    """Distinct values of `x` (values closer than 1e-9 of the span are one) and the index
    of each entry among them."""
    u = np.unique(x)
    tol = 1e-9 * max(1.0, float(u[-1] - u[0]))
    keep = np.concatenate([[True], np.diff(u) > tol])
    ax = u[keep]
    k = np.searchsorted(ax, x + tol, side="right") - 1
    return ax, k


def _table_errors(i_d, i_q, psi_d, psi_q) -> list[str]:
    """Each flux must increase with its own current between neighbouring grid points."""
    out = []
    for flux, cur, diff in (("psi_d", "i_d", np.diff(psi_d, axis=0)),
                            ("psi_q", "i_q", np.diff(psi_q, axis=1))):
        bad = np.argwhere(diff <= 0)
        if bad.size:
            if cur == "i_d":
                where = [f"i_d {i_d[a]:.6g} -> {i_d[a + 1]:.6g} A at i_q = {i_q[b]:.6g} A "
                         f"({flux} {psi_d[a, b]:.6g} -> {psi_d[a + 1, b]:.6g} V s)"
                         for a, b in bad]
            else:
                where = [f"i_q {i_q[b]:.6g} -> {i_q[b + 1]:.6g} A at i_d = {i_d[a]:.6g} A "
                         f"({flux} {psi_q[a, b]:.6g} -> {psi_q[a, b + 1]:.6g} V s)"
                         for a, b in bad]
            out.append(f"{flux} does not increase with {cur} (d {flux}/d {cur} <= 0) "
                       f"between {_list(where)}; each flux must increase with its own "
                       "current (a positive incremental self-inductance)")
    return out


def _node_inductances(model: AbstractMagneticModel, i_d, i_q):
    dd, qq = np.meshgrid(np.asarray(i_d, float), np.asarray(i_q, float), indexing="ij")
    nodes, _ = _evaluate(model, jnp.asarray(dd), jnp.asarray(qq), jnp.zeros((1, 2)))
    return dd, qq, *(np.asarray(x) for x in nodes)


@eqx.filter_jit
def _evaluate(model: AbstractMagneticModel, dd, qq, points):
    """One compiled evaluation for `check_flux_map`: the incremental inductances at the
    nodes `dd`, `qq` (A) and, at each of `points` (A, (n, 2)), the incremental inductances
    `(n, 4)`, the apparent `(L_d, L_q)` `(n, 2)` and the PM flux `(n,)`."""
    _, _, *nodes = model.flux_and_inductance(dd, qq)
    _, _, *L = model.flux_and_inductance(points[:, 0], points[:, 1])
    L_d, L_q, psi_f = model.apparent_inductance(points)
    return tuple(nodes), (jnp.stack(L, -1), jnp.stack([L_d, L_q], -1), psi_f)


def _inductance_errors(model: AbstractMagneticModel, i_d=None, i_q=None,
                       nodes=None) -> list[str]:
    """The incremental inductance matrix (its symmetric part) must be positive definite
    at every grid node (`nodes`: the node currents and inductances, when known)."""
    if i_d is None:
        i_d, i_q = model.i_d, model.i_q
    dd, qq, l_dd, l_dq, l_qd, l_qq = nodes or _node_inductances(model, i_d, i_q)
    b = 0.5 * (l_dq + l_qd)
    bad = np.argwhere(~((l_dd > 0) & (l_dd * l_qq - b * b > 0)))
    if not bad.size:
        return []
    where = [f"{_pt(dd[a, c], qq[a, c])} (L_dd {1e3 * l_dd[a, c]:.4g}, L_dq "
             f"{1e3 * l_dq[a, c]:.4g}, L_qd {1e3 * l_qd[a, c]:.4g}, L_qq "
             f"{1e3 * l_qq[a, c]:.4g} mH)" for a, c in bad]
    return [f"incremental inductance matrix d psi_dq / d i_dq not positive definite at "
            f"{_list(where)}; a physical map has L_dd > 0 and L_dd L_qq > ((L_dq + L_qd)/2)^2 "
            "everywhere (the magnetic energy is convex)"]


def read_flux_map(path) -> FluxMap:
    """The `FluxMap` in the file `path`: a CSV (header `i_d,i_q,psi_d,psi_q`, A, A, V s,
    V s, one row per point of a rectangular grid, any row order) or an NPZ (the same four
    1-D arrays, or the axes `i_d` `(n_d,)`, `i_q` `(n_q,)` and the tables `psi_d`, `psi_q`
    `(n_d, n_q)`). Flux linkages are peak values of the amplitude-invariant dq transform,
    `psi_d` along the magnet.

    Raises `FluxMapError` (a `ValueError`) naming the file, what is wrong, where and what
    is allowed: missing columns, a value that is not a finite number (with its row), a
    non-rectangular grid (the missing points), duplicate grid points, fewer than 4 values
    per axis, a flux that does not increase with its own current (where), an incremental
    inductance matrix that is not positive definite (where); `OSError` if the file cannot
    be read.
    """
    source = os.fspath(path)
    r = _Map(source)
    if source.lower().endswith(".npz"):
        try:
            data = np.load(source, allow_pickle=False)
        except ValueError as e:
            r.fail(f"not a readable NPZ file ({e})")
        with data:
            arrays = {k: np.asarray(data[k]) for k in data.files}
        missing = [c for c in COLUMNS if c not in arrays]
        if missing:
            r.fail(f"missing array{'s' if len(missing) > 1 else ''} {', '.join(missing)} "
                   f"(found {', '.join(sorted(arrays)) or 'none'}); a flux-map NPZ holds "
                   f"{', '.join(COLUMNS)}: four 1-D columns, or the axes i_d (n_d,), i_q "
                   "(n_q,) and the tables psi_d, psi_q (n_d, n_q)")
        i_d, i_q, psi_d, psi_q = (arrays[c].astype(float) for c in COLUMNS)
        if psi_d.ndim == 2 or psi_q.ndim == 2:
            return r.from_tables(i_d, i_q, psi_d, psi_q)
        n = {c: arrays[c].shape for c in COLUMNS}
        if any(len(s) != 1 for s in n.values()) or len(set(n.values())) != 1:
            r.fail(f"arrays of shapes {n}; a flux-map NPZ holds either four 1-D columns "
                   "of equal length or the axes i_d (n_d,), i_q (n_q,) and the tables "
                   "psi_d, psi_q (n_d, n_q)")
        where = [f"entry {k}" for k in range(i_d.size)]
        return r.from_tables(*r.from_columns(where, (i_d, i_q, psi_d, psi_q)))
    with open(source, encoding="utf-8-sig") as f:
        text = f.read()
    where, cols = r.csv_columns(text)
    return r.from_tables(*r.from_columns(where, cols))


def flux_map_csv(flux_map: FluxMap) -> str:
    """The CSV text of `flux_map` (header `i_d,i_q,psi_d,psi_q`, rows ordered by i_d then
    i_q, every number written exactly): `read_flux_map` of it gives back the same map."""
    i_d, i_q = np.asarray(flux_map.i_d, float), np.asarray(flux_map.i_q, float)
    psi_d, psi_q = np.asarray(flux_map.psi_d, float), np.asarray(flux_map.psi_q, float)
    lines = [",".join(COLUMNS)]
    for a, x in enumerate(i_d):
        for b, y in enumerate(i_q):
            lines.append(",".join(repr(float(v)) for v in (x, y, psi_d[a, b], psi_q[a, b])))
    return "\n".join(lines) + "\n"


@dataclasses.dataclass(frozen=True)
class FluxMapReport:
    """What `check_flux_map` found (SI units: A, V s, H; inductances as `(L_dd, L_dq,
    L_qd, L_qq)`, apparent ones as `(L_d, L_q)`).

    - `grid`: `(n_d, n_q)` grid points of a `FluxMap` (`None` for an analytical model),
      `i_d_range`, `i_q_range`: its current range (A).
    - `psi_f`: PM flux at zero current (V s); `L_inc_zero`, `L_app_zero`: incremental
      and apparent inductances there (H).
    - `i_max`: the current limit checked (A, or `None`); `psi_f_rated`, `L_inc_rated`,
      `L_app_rated`: the same at `i_max` on the q axis (`None` without `i_max`).
    - `reciprocity`: the largest relative asymmetry |L_dq - L_qd| / sqrt(L_dd L_qq) over
      the grid's nodes, `reciprocity_at`: where (A), `reciprocity_tol`: the tolerance.
    - `covers`: whether the grid covers i_d in [-i_max, 0], i_q in [-i_max, i_max]
      (`None` without `i_max` or without a grid).
    - `warnings`, `errors`: messages (an error: a map the plant should not run on).
    """

    grid: tuple[int, int] | None
    i_d_range: tuple[float, float] | None
    i_q_range: tuple[float, float] | None
    psi_f: float
    L_inc_zero: tuple[float, float, float, float]
    L_app_zero: tuple[float, float]
    i_max: float | None
    psi_f_rated: float | None
    L_inc_rated: tuple[float, float, float, float] | None
    L_app_rated: tuple[float, float] | None
    reciprocity: float
    reciprocity_at: tuple[float, float]
    reciprocity_tol: float
    covers: bool | None
    warnings: tuple[str, ...]
    errors: tuple[str, ...]

    def lines(self) -> list[str]:
        """The report as console lines."""
        mh = lambda L: ", ".join(f"{n} {1e3 * v:.4g}" for n, v in zip(  # noqa: E731
            ("L_dd", "L_dq", "L_qd", "L_qq"), L)) + " mH"
        out = []
        if self.grid is not None:
            out.append(f"flux map: {self.grid[0]} x {self.grid[1]} grid, i_d "
                       f"{self.i_d_range[0]:.4g}..{self.i_d_range[1]:.4g} A, i_q "
                       f"{self.i_q_range[0]:.4g}..{self.i_q_range[1]:.4g} A")
        else:
            out.append("magnetic model: analytical (no grid)")
        out += [f"  zero current: psi_f {self.psi_f:.4g} V s, incremental {mh(self.L_inc_zero)},"
                f" apparent L_d {1e3 * self.L_app_zero[0]:.4g}, L_q "
                f"{1e3 * self.L_app_zero[1]:.4g} mH"]
        if self.i_max is not None:
            out.append(f"  rated current (i_q = i_max = {self.i_max:.4g} A): psi_f "
                       f"{self.psi_f_rated:.4g} V s, incremental {mh(self.L_inc_rated)}, "
                       f"apparent L_d {1e3 * self.L_app_rated[0]:.4g}, L_q "
                       f"{1e3 * self.L_app_rated[1]:.4g} mH")
        out.append(f"  reciprocity: largest |L_dq - L_qd| / sqrt(L_dd L_qq) "
                   f"{100 * self.reciprocity:.3g} % at "
                   f"{_pt(*self.reciprocity_at)} (tolerance {100 * self.reciprocity_tol:g} %)")
        if self.covers is not None:
            out.append(f"  covers the current limit i_max = {self.i_max:.4g} A: "
                       f"{'yes' if self.covers else 'no'}")
        out += [f"warning: {w}" for w in self.warnings]
        out += [f"error: {e}" for e in self.errors]
        return out


def check_flux_map(flux_map: AbstractMagneticModel, i_max=None,
                   reciprocity_tol: float = RECIPROCITY_TOL) -> FluxMapReport:
    """Check a magnetic model (a `FluxMap`, or any `AbstractMagneticModel`) and report what
    it holds: grid and current range, PM flux and incremental and apparent inductances at
    zero current and (with the current limit `i_max`, A) at `i_max` on the q axis, the
    largest reciprocity asymmetry |d psi_d/d i_q - d psi_q/d i_d| / sqrt(L_dd L_qq) over
    the grid's nodes (a warning above `reciprocity_tol`, default 5 %, with the measured
    value and where), whether the grid covers the drive's current range (i_d in
    [-i_max, 0], i_q in [-i_max, i_max]; a warning otherwise: outside the grid the flux is
    extended linearly with the incremental inductance of the grid's edge), and as errors
    a flux that does not increase with its own current or an incremental inductance
    matrix that is not positive definite. An analytical model is checked on a 21 x 21
    grid over [-i_max, i_max]^2 (only at zero current without `i_max`).
    Returns a `FluxMapReport`."""
    if not isinstance(flux_map, AbstractMagneticModel):
        raise TypeError(f"`check_flux_map(flux_map=...)` must be a FluxMap or another "
                        f"AbstractMagneticModel; got {type(flux_map).__name__}.")
    if i_max is not None and not (math.isfinite(float(i_max)) and float(i_max) > 0):
        raise ValueError(f"`check_flux_map(i_max=...)` (A) must be a finite number > 0 or "
                         f"None; got {i_max!r}.")
    i_max = None if i_max is None else float(i_max)
    model = flux_map
    warnings, errors = [], []
    is_map = isinstance(model, FluxMap)
    if is_map:
        i_d, i_q = np.asarray(model.i_d, float), np.asarray(model.i_q, float)
        errors += _table_errors(i_d, i_q, np.asarray(model.psi_d), np.asarray(model.psi_q))
    elif i_max is not None:
        i_d = i_q = np.linspace(-i_max, i_max, 21)
    else:
        i_d = i_q = np.zeros(1)
    dd, qq = np.meshgrid(i_d, i_q, indexing="ij")
    nodes, points = _evaluate(model, jnp.asarray(dd), jnp.asarray(qq),
                              jnp.asarray([[0.0, 0.0], [0.0, i_max or 0.0]]))
    l_dd, l_dq, l_qd, l_qq = (np.asarray(x) for x in nodes)
    errors += _inductance_errors(model, i_d, i_q, (dd, qq, l_dd, l_dq, l_qd, l_qq))
    L_inc, L_app, psi_f = (np.asarray(x) for x in points)
    L_inc0, L_app0, psi_f0 = tuple(map(float, L_inc[0])), tuple(map(float, L_app[0])), \
        float(psi_f[0])
    L_incr = L_appr = psi_fr = None
    if i_max is not None:
        L_incr, L_appr, psi_fr = tuple(map(float, L_inc[1])), tuple(map(float, L_app[1])), \
            float(psi_f[1])

    asym = np.abs(l_dq - l_qd) / np.sqrt(np.abs(l_dd * l_qq))
    k = np.unravel_index(int(np.nanargmax(asym)), asym.shape)
    rec, rec_at = float(asym[k]), (float(dd[k]), float(qq[k]))
    if rec > reciprocity_tol:
        warnings.append(
            f"the map is not reciprocal: |d psi_d/d i_q - d psi_q/d i_d| / sqrt(L_dd L_qq) "
            f"reaches {100 * rec:.3g} % at {_pt(*rec_at)} (L_dq {1e3 * float(l_dq[k]):.4g} "
            f"mH, L_qd {1e3 * float(l_qd[k]):.4g} mH), above the tolerance "
            f"{100 * reciprocity_tol:g} %; a lossless magnetic field has L_dq = L_qd, so "
            "the map's errors (mesh, measurement, a wrong dq convention) are at least that")
    covers = None
    if is_map and i_max is not None:
        covers = bool(i_d[0] <= -i_max and i_d[-1] >= 0.0
                      and i_q[0] <= -i_max and i_q[-1] >= i_max)
        if not covers:
            warnings.append(
                f"the grid (i_d {i_d[0]:.4g}..{i_d[-1]:.4g} A, i_q {i_q[0]:.4g}.."
                f"{i_q[-1]:.4g} A) does not cover the drive's current range under the "
                f"limit i_max = {i_max:.4g} A (i_d -{i_max:.4g}..0 A, i_q -{i_max:.4g}.."
                f"{i_max:.4g} A): outside the grid the flux is extended linearly with the "
                "incremental inductance of the grid's edge (the saturation stops growing "
                "there)")
    return FluxMapReport(
        grid=(len(i_d), len(i_q)) if is_map else None,
        i_d_range=(float(i_d[0]), float(i_d[-1])) if is_map else None,
        i_q_range=(float(i_q[0]), float(i_q[-1])) if is_map else None,
        psi_f=psi_f0, L_inc_zero=L_inc0, L_app_zero=L_app0, i_max=i_max,
        psi_f_rated=psi_fr, L_inc_rated=L_incr, L_app_rated=L_appr,
        reciprocity=rec, reciprocity_at=rec_at, reciprocity_tol=float(reciprocity_tol),
        covers=covers, warnings=tuple(warnings), errors=tuple(errors))
