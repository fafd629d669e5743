r"""Feasibility maps of the zhang2022 ESO flux-gain design (Fig. 1).

A design $(\zeta_1, \omega_1/|\omega_0|)$ at an operating point (speed, current, parameter
mismatch) is

- **feasible** (`status = 0`) if every equilibrium of the error dynamics zhang2022 (11) other than
  the designed one is unstable, so the error cannot settle at a static angle error;
- **infeasible** (`status = 1`) if at least one of them is stable (its angle is reported:
  the static position error the observer can lock to);
- **no equilibrium** (`status = 2`, only with parameter mismatch): the angle error
  cannot settle anywhere, the estimate drifts;
- **degenerate** (`status = -1`): the analysis does not apply or failed: $\omega_0 = 0$,
  $\omega_1 = 0$ (ratio 0: $\det(\omega_0J + G_1) = \omega_1^2 = 0$, a continuum of flux
  errors), $\psi_{a0} = 0$, a double root at the origin, non-finite values.

"Designed equilibrium": $\tilde\theta = 0$ with matched parameters; with mismatch the
equilibrium closest to $\tilde\theta = 0$. Whether it is itself stable is reported
separately (`principal_stable`; it is Hurwitz for every $\zeta_1, \omega_1, \zeta_2,
\omega_2 > 0$ with matched parameters, by zhang2022 (16)/(18)). The classification of
one point from its equilibria, and `classify` for any observer, are in
`pmsmjax.analysis._classify`; `design_map` maps any observer over two of its design
parameters.

Two methods:

- `"closed_form"` (matched parameters, linear feedback): the quartic route zhang2022
  (34)-(36) and the Jacobian zhang2022 (37) in closed form (`pmsmjax.analysis._closed_form`):
  millions of designs per second on one CPU core.
- `"general"`: `eso_equilibria` (bracketing + `optimistix` bisection on the full
  right-hand side, Jacobian by `jax.jacfwd`), vmapped. Works with parameter mismatch and
  fal feedback; about 10^3 - 10^4 designs per second.

`"auto"` picks `"closed_form"` when it applies. With the minimum-norm gains zhang2022 (25) the
equilibria do not depend on $\zeta_2$, $\omega_2$ (the condition $g_3 f = 0$ fixes only
the direction of $f$), but their stability can.
"""


from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._plant._params import Drive, PMSMParams
from ..observers import OperatingPoint, eso_gains, psi_a, zhang38
from ._args import as_arrays, check_observer
from ._classify import DesignClass, _class_from_equilibria, _resolve_classify
from ._closed_form import _closed_form_jit
from ._equilibria import eso_equilibria
from ._generic import equilibria_traced
from ._linearize import check_frame


METHODS = ("auto", "closed_form", "general")

# ---------------------------------------------------------------------------------------
# General route per design
# ---------------------------------------------------------------------------------------

def _general_classify(w0, i0, zeta1, ratio, zeta2, w2, motor, motor_hat, a, eta, frame,
                      n_grid, max_roots):
    mh = motor if motor_hat is None else motor_hat
    g = eso_gains(psi_a(mh, i0), w0, zeta1, ratio * jnp.abs(w0), zeta2, w2)
    eq = eso_equilibria(w0, i0, g, motor, motor_hat, a=a, eta=eta, frame=frame,
                        n_grid=n_grid, max_roots=max_roots)
    return _class_from_equilibria(eq, ~(ratio > 0))


@eqx.filter_jit
def _general_batch(w0, i0, zeta1, ratio, zeta2, w2, motor, motor_hat, a, eta, frame,
                   n_grid, max_roots):
    fn = lambda *v: _general_classify(*v, motor, motor_hat, a, eta, frame, n_grid,  # noqa: E731
                                      max_roots)
    return jax.vmap(fn)(w0, i0, zeta1, ratio, zeta2, w2)


# ---------------------------------------------------------------------------------------
# Public entry points
# ---------------------------------------------------------------------------------------

def _check_array(owner, name, x, *, nonneg=False, nonzero=False, unit=""):
    a = np.asarray(x, dtype=float)
    u = f" ({unit})" if unit else ""
    if a.size == 0:
        raise ValueError(f"`{owner}({name}=...)`{u} is empty: nothing to evaluate.")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"`{owner}({name}=...)`{u} must be finite; it contains NaN or inf.")
    if nonneg and np.any(a < 0):
        raise ValueError(f"`{owner}({name}=...)`{u} must be >= 0; got min {a.min()!r}.")
    if nonzero and np.any(a == 0):
        raise ValueError(
            f"`{owner}({name}=...)`{u} must not contain 0: the gains (17) contain "
            f"w1^2/w0 and the error dynamics have a continuum of equilibria at standstill."
        )
    return a


def _resolve_method(owner, method, motor_hat, a):
    if method not in METHODS:
        raise ValueError(
            f"`{owner}(method=...)` must be one of {', '.join(map(repr, METHODS))}; "
            f"got {method!r}.")
    linear = isinstance(a, int | float) and float(a) == 1.0
    simple = motor_hat is None and linear
    if method == "closed_form" and not simple:
        raise ValueError(
            f"`{owner}(method='closed_form')` needs matched parameters (motor_hat=None) "
            f"and linear feedback (a=1); use method='general'.")
    return "closed_form" if (method == "auto" and simple) else (
        "general" if method == "auto" else method)


def classify_designs(motor: PMSMParams, w0, i_dq, zeta1, ratio, *, zeta2=1.0,
                     w2=2 * math.pi * 50.0, motor_hat: PMSMParams | None = None, a=1.0,
                     eta=1.0, frame: str = "observer", method: str = "auto",
                     n_grid: int = 256, max_roots: int = 8, dtype=None) -> DesignClass:
    """Classify ESO flux-gain designs at operating points (SI units, any batch shape).

    **Arguments:**

    - `motor`: the plant's `PMSMParams`; `motor_hat`: the observer's model (mismatch),
      default `motor`.
    - `w0`: electrical speed (rad/s), nonzero; `i_dq`: current in the estimator frame
      (A, last axis 2); `zeta1` (-), `ratio` = w1/|w0| (-); `zeta2` (-), `w2` (rad/s).
      All broadcast against each other (`i_dq` without its last axis).
    - `a`, `eta`: fal feedback (`a = 1`: linear). `frame`: `"observer"` or `"paper"`.
    - `method`: `"auto"`, `"closed_form"` or `"general"` (module docstring).
    - `n_grid`, `max_roots`: of the general route. `dtype`: computation dtype (default
      float64; float32 works for the closed form).

    Returns a `DesignClass` with the broadcast batch shape. Concrete inputs are checked
    (empty or NaN raise `ValueError`); `w0 = 0` (the gains zhang2022 (17) contain w1^2/w0 and the
    error dynamics have a continuum of equilibria at standstill) and, under
    `jit`/`vmap`, other bad points get status -1.
    """
    check_frame("classify_designs", frame)
    method = _resolve_method("classify_designs", method, motor_hat, a)
    for name, v in (("w0", w0), ("i_dq", i_dq), ("zeta1", zeta1), ("ratio", ratio),
                    ("zeta2", zeta2), ("w2", w2)):
        if not isinstance(v, jax.core.Tracer):
            _check_array("classify_designs", name, v,
                         nonneg=name in ("zeta1", "ratio", "zeta2", "w2"))
    dtype = jnp.float64 if dtype is None else dtype
    i_dq = jnp.asarray(i_dq, dtype)
    if i_dq.shape[-1:] != (2,):
        raise ValueError(f"`classify_designs(i_dq=...)` must have a last axis of length 2 "
                         f"(i_d, i_q); got shape {i_dq.shape}.")
    w0, zeta1, ratio, zeta2, w2 = (jnp.asarray(v, dtype) for v in (w0, zeta1, ratio, zeta2,
                                                                      w2))
    if method == "closed_form":
        return _closed_form_jit(w0, i_dq[..., 0], i_dq[..., 1], zeta1, ratio, zeta2, w2,
                                jnp.asarray(motor.L_d, dtype), jnp.asarray(motor.L_q, dtype),
                                jnp.asarray(motor.psi_f, dtype), frame=frame)
    # Arrays, not Python floats, so that new parameter values do not recompile.
    motor, motor_hat = as_arrays(motor, dtype), as_arrays(motor_hat, dtype)
    a = 1.0 if (isinstance(a, int | float) and float(a) == 1.0) else jnp.asarray(a, dtype)
    eta = jnp.asarray(eta, dtype)
    shape = jnp.broadcast_shapes(w0.shape, i_dq.shape[:-1], zeta1.shape, ratio.shape,
                                 zeta2.shape, w2.shape)
    flat = [jnp.broadcast_to(v, shape).reshape(-1) for v in (w0, zeta1, ratio, zeta2, w2)]
    i0 = jnp.broadcast_to(i_dq, shape + (2,)).reshape(-1, 2)
    res = _general_batch(flat[0], i0, flat[1], flat[2], flat[3], flat[4], motor, motor_hat,
                         a, eta, frame, n_grid, max_roots)
    return jax.tree_util.tree_map(lambda v: v.reshape(shape + v.shape[1:]), res)


class FeasibilityMap(eqx.Module):
    """A feasibility map over (speed, load, x, y), x and y two named design parameters of
    the observer (zhang2022 Fig. 1: x = zeta1, y = ratio).

    Arrays have shape `(n_speed, n_load, n_x, n_y)` (`theta_deg`, `stable` one more axis
    for the equilibria). Angles in degrees.

    - `status`, `n_nonzero`, `principal_stable`: as in `DesignClass`;
      `principal_theta_deg`: the designed equilibrium's angle (deg; nonzero only with
      mismatch).
    - `stable_theta_deg`: static position error of infeasible designs (deg), else NaN.
    - `theta_deg`, `stable`: every non-designed equilibrium and its stability.
    - `speeds`: speeds (p.u. of `w_rated`); `i_dq`: currents `(n_load, 2)` (p.u. of
      `I_b`); `x`, `y`: the design axes (SI values of the parameters named `x_name`,
      `y_name`); `zeta1`, `ratio` are the same arrays when the axes are zhang2022's.
    - `w_rated` (rad/s), `I_b` (A): the bases used. `method`, `frame`: how it was made;
      `observer`: the registry class name of the observer.
    """

    status: jnp.ndarray
    n_nonzero: jnp.ndarray
    stable_theta_deg: jnp.ndarray
    theta_deg: jnp.ndarray
    stable: jnp.ndarray
    principal_stable: jnp.ndarray
    principal_theta_deg: jnp.ndarray
    speeds: np.ndarray
    i_dq: np.ndarray
    x: np.ndarray
    y: np.ndarray
    w_rated: float
    I_b: float
    method: str = eqx.field(static=True)
    frame: str = eqx.field(static=True)
    x_name: str = eqx.field(static=True, default="zeta1")
    y_name: str = eqx.field(static=True, default="ratio")
    observer: str = eqx.field(static=True, default="LESOObserver")

    def _axis(self, name):
        if self.x_name == name:
            return self.x
        if self.y_name == name:
            return self.y
        raise AttributeError(f"this map's axes are {self.x_name!r} and {self.y_name!r}, "
                             f"not {name!r}")

    @property
    def zeta1(self):
        return self._axis("zeta1")

    @property
    def ratio(self):
        return self._axis("ratio")

    def schedule38(self):
        """The design zhang2022 (38) (`pmsmjax.observers.zhang38`) at each speed as
        `(zeta1, ratio)` arrays of shape (n_speed,): zeta1 (-) and ratio = w1/|w0| (-), a
        single point per speed (at zero speed the limit w0 -> 0)."""
        w0 = np.asarray(self.speeds, dtype=float) * float(self.w_rated)  # rad/s
        w0 = np.where(w0 == 0, np.finfo(float).tiny, w0)  # w1/|w0| -> its limit at 0
        zeta1, w1 = zhang38(w0, float(self.w_rated))
        return np.asarray(zeta1), np.asarray(w1) / np.abs(w0)

    def fraction(self, status: int = 0):
        """Fraction of designs with the given status, per (speed, load)."""
        return np.mean(np.asarray(self.status) == status, axis=(-2, -1))

    def summary(self) -> str:
        """One line per (speed, load): fractions feasible / infeasible / degenerate and
        the range of the static errors."""
        lines = []
        st = np.asarray(self.status)
        th = np.asarray(self.stable_theta_deg)
        for i, s in enumerate(self.speeds):
            for j, cur in enumerate(self.i_dq):
                a = st[i, j]
                t = th[i, j][np.isfinite(th[i, j])]
                rng = (f", static error {t.min():.2f}..{t.max():.2f} deg" if t.size else "")
                lines.append(
                    f"w0 = {s:g} p.u., i_dq = ({cur[0]:g}, {cur[1]:g}) p.u.: feasible "
                    f"{np.mean(a == 0):.1%}, infeasible {np.mean(a == 1):.1%}, degenerate "
                    f"{np.mean(a == -1):.1%}{rng}")
        return "\n".join(lines)


def feasibility_map(drive: Drive, speeds, zeta1, ratio, *, i_dq=(0.0, 0.0),
                    motor_hat: PMSMParams | None = None, zeta2=1.0,
                    w2=2 * math.pi * 50.0, a=1.0, eta=1.0, frame: str = "observer",
                    method: str = "auto", n_grid: int = 256, max_roots: int = 8,
                    dtype=None) -> FeasibilityMap:
    """Feasibility map of the flux-gain design over a `(zeta1, ratio)` grid (Fig. 1).

    **Arguments:**

    - `drive`: a `Drive` (its three-phase motor is the plant; `w_rated` and `base.I_b`
      give the per-unit bases).
    - `speeds`: electrical speeds in p.u. of `drive.w_rated`, 1-D, nonzero.
    - `zeta1`: flux damping values (-), 1-D, >= 0 (the paper: [0, 5]).
    - `ratio`: w1/|w0| values (-), 1-D, >= 0 (the paper: [0, 2]); 0 gives status -1.
    - `i_dq`: controlled current(s) in the estimator frame, p.u. of `drive.base.I_b`:
      `(2,)` or `(n_load, 2)`.
    - `motor_hat`: the observer's model (parameter mismatch), default the plant.
    - `zeta2`, `w2` (rad/s): speed/angle design zhang2022 (25). `a`, `eta` (V s): fal feedback.
    - `frame`, `method`, `n_grid`, `max_roots`, `dtype`: see `classify_designs`.

    One jitted, vmapped call. Returns a `FeasibilityMap`.
    """
    if not isinstance(drive, Drive):
        raise ValueError(f"`feasibility_map(drive=...)` must be a `Drive` (e.g. "
                         f"`pj.preset('zhang750')`); got {type(drive).__name__}.")
    check_frame("feasibility_map", frame)
    _resolve_method("feasibility_map", method, motor_hat, a)
    sp = _check_array("feasibility_map", "speeds", speeds, nonzero=True, unit="p.u.")
    z = _check_array("feasibility_map", "zeta1", zeta1, nonneg=True)
    r = _check_array("feasibility_map", "ratio", ratio, nonneg=True)
    cur = _check_array("feasibility_map", "i_dq", i_dq, unit="p.u.")
    for name, v in (("speeds", sp), ("zeta1", z), ("ratio", r)):
        if v.ndim != 1:
            raise ValueError(f"`feasibility_map({name}=...)` must be 1-D; got shape {v.shape}.")
    cur = cur.reshape(-1, 2) if cur.shape[-1:] == (2,) and cur.ndim <= 2 else None
    if cur is None:
        raise ValueError("`feasibility_map(i_dq=...)` must have shape (2,) or (n_load, 2) "
                         "(i_d, i_q in p.u.).")
    motor = drive.three_phase_motor
    w_r, I_b = float(drive.w_rated), float(drive.base.I_b)
    w0 = (sp * w_r)[:, None, None, None]
    i_si = (cur * I_b)[None, :, None, None, :]
    res = classify_designs(motor, w0, i_si, z[None, None, :, None], r[None, None, None, :],
                           zeta2=zeta2, w2=w2, motor_hat=motor_hat, a=a, eta=eta,
                           frame=frame, method=method, n_grid=n_grid, max_roots=max_roots,
                           dtype=dtype)
    shape = (len(sp), len(cur), len(z), len(r))
    bc = lambda v: jnp.broadcast_to(v, shape + v.shape[len(shape):])  # noqa: E731
    return FeasibilityMap(
        status=bc(res.status), n_nonzero=bc(res.n_nonzero),
        stable_theta_deg=bc(jnp.degrees(res.stable_theta)),
        theta_deg=bc(jnp.degrees(res.theta)), stable=bc(res.stable),
        principal_stable=bc(res.principal_stable),
        principal_theta_deg=bc(jnp.degrees(res.principal_theta)), speeds=sp, i_dq=cur,
        x=z, y=r,
        w_rated=w_r, I_b=I_b, method=_resolve_method("feasibility_map", method, motor_hat, a),
        frame=frame)



def design_map(observer, drive: Drive, speeds, x, y, *, i_dq=(0.0, 0.0), plant=None,
               method: str = "auto", dtype=None, **options) -> FeasibilityMap:
    """Feasibility map of `observer` over two named design parameters (any observer).

    **Arguments:**

    - `observer`: any `AbstractObserver` (e.g. `observers.make_observer("leso", drive)`);
      its `motor` is its model (observer-model mismatch: `observer.with_motor(...)`).
    - `drive`: the `Drive`: its machine is the plant unless `plant` is given, and its
      `w_rated`, `base.I_b` are the per-unit bases.
    - `speeds`: electrical speeds in p.u. of `drive.w_rated`, 1-D.
    - `x`, `y`: `(name, values)` pairs: a design parameter of the observer (its
      `design_units`) and its 1-D values (SI units as there).
    - `i_dq`: current(s) in the estimated frame, p.u. of `drive.base.I_b`: `(2,)` or
      `(n_load, 2)`.
    - `plant`: the true machine; None = the drive's.
    - `method`: `"auto"` uses the family's closed form when the observer's model equals
      the plant's (compared by value) and one exists (zhang2022 (34)-(36) for the ESO/LESO), else
      `"generic"`; `"closed_form"` / `"generic"` force one.
    - `dtype`: computation dtype (default float64). `options`: passed to `equilibria`.

    One jitted, vmapped call over the whole grid. Returns a `FeasibilityMap`.
    """
    check_observer("design_map", observer)
    if not isinstance(drive, Drive):
        raise ValueError(f"`design_map(drive=...)` must be a `Drive`; got "
                         f"{type(drive).__name__}.")
    axes = []
    for arg, pair in (("x", x), ("y", y)):
        if not (isinstance(pair, tuple | list) and len(pair) == 2
                and isinstance(pair[0], str)):
            raise ValueError(f"`design_map({arg}=...)` must be a (name, values) pair; got "
                             f"{pair!r}.")
        name, vals = pair
        if name not in observer.design_units:
            raise ValueError(
                f"`design_map({arg}=...)`: {type(observer).__name__} has no design "
                f"parameter {name!r}; it has {', '.join(observer.design_units)}.")
        v = _check_array("design_map", arg, vals)
        if v.ndim != 1:
            raise ValueError(f"`design_map({arg}=...)` values must be 1-D; got shape "
                             f"{v.shape}.")
        axes.append((name, v))
    (xn, xv), (yn, yv) = axes
    if xn == yn:
        raise ValueError(f"`design_map`: x and y must be different parameters; both are "
                         f"{xn!r}.")
    sp = _check_array("design_map", "speeds", speeds, unit="p.u.")
    cur = _check_array("design_map", "i_dq", i_dq, unit="p.u.")
    if sp.ndim != 1:
        raise ValueError(f"`design_map(speeds=...)` must be 1-D; got shape {sp.shape}.")
    if not (cur.shape[-1:] == (2,) and cur.ndim <= 2):
        raise ValueError("`design_map(i_dq=...)` must have shape (2,) or (n_load, 2) "
                         "(i_d, i_q in p.u.).")
    cur = cur.reshape(-1, 2)
    dtype = jnp.float64 if dtype is None else dtype
    w_r, I_b = float(drive.w_rated), float(drive.base.I_b)
    obs_in, plant_in, resolved = _design_map_setup(observer, drive, sp, (xn, xv), (yn, yv),
                                                   cur, plant, method, dtype)
    grid = np.stack(np.meshgrid(sp * w_r, np.arange(len(cur)), xv, yv, indexing="ij"),
                    -1).reshape(-1, 4)
    i_all = (cur * I_b)[grid[:, 1].astype(int)]
    res = _design_map_batch(obs_in, plant_in,
                            jnp.asarray(grid[:, 0], dtype), jnp.asarray(i_all, dtype),
                            jnp.asarray(grid[:, 2], dtype), jnp.asarray(grid[:, 3], dtype),
                            xn, yn, resolved, options)
    shape = (len(sp), len(cur), len(xv), len(yv))
    res = jax.tree_util.tree_map(lambda v: v.reshape(shape + v.shape[1:]), res)
    return FeasibilityMap(
        status=res.status, n_nonzero=res.n_nonzero,
        stable_theta_deg=jnp.degrees(res.stable_theta), theta_deg=jnp.degrees(res.theta),
        stable=res.stable, principal_stable=res.principal_stable,
        principal_theta_deg=jnp.degrees(res.principal_theta), speeds=sp, i_dq=cur,
        x=xv, y=yv, w_rated=w_r, I_b=I_b, method=resolved, frame="observer",
        x_name=xn, y_name=yn, observer=type(observer).__name__)


def _design_map_setup(observer, drive, sp, x, y, cur, plant, method, dtype):
    """What `design_map` evaluates at each point: `(observer, plant, method)` for
    `_design_point` (the closed form or the generic route, resolved on a probe design)."""
    (xn, xv), (yn, yv) = x, y
    w_r, I_b = float(drive.w_rated), float(drive.base.I_b)
    plant_ = drive.three_phase_motor if plant is None else plant
    # the closed form needs the observer's model to be the plant's
    matched = bool(eqx.tree_equal(as_arrays(plant_, dtype), as_arrays(observer.motor, dtype)))
    # probe the design's structure with the largest values (a zero, allowed on an axis,
    # is refused by some design constructors outside a trace)
    probe = observer.with_design(**{xn: float(np.max(xv)), yn: float(np.max(yv))})
    resolved = _resolve_classify("design_map", probe, None if matched else plant_, method,
                                 jnp.asarray(sp[0] * w_r, dtype),
                                 jnp.asarray(cur[0] * I_b, dtype))
    # (the closed form decides on the design's structure, e.g. n2 = n3 = 0, so the
    # observer's Python-number leaves stay concrete there)
    obs_in = observer if resolved == "closed_form" else as_arrays(observer, dtype)
    return obs_in, as_arrays(plant_, dtype), resolved


def _design_point(observer, plant, w, i, a, b, xn, yn, method, options) -> DesignClass:
    """Classification of one design `xn = a`, `yn = b` at speed `w` (rad/s) and current
    `i` (A): the body of `design_map` (and of the command line's sweep of it)."""
    obs = observer.with_design(**{xn: a, yn: b})
    if method == "closed_form":
        return obs.fast_classify(w, i)
    eq = equilibria_traced(obs, plant, OperatingPoint(w, i), **options)
    return _class_from_equilibria(eq)


@eqx.filter_jit
def _design_map_batch(observer, plant, w0, i0, xv, yv, xn, yn, method, options):
    def one(w, i, a, b):
        return _design_point(observer, plant, w, i, a, b, xn, yn, method, options)

    return jax.vmap(one)(w0, i0, xv, yv)
