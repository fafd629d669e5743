r"""Analysis at an operating point of a saturated machine (`PMSMParams.magnetic` set).

On a saturated plant the observer keeps its constant model (the drive's `L_d`, `L_q`,
`psi_f`, `observer.motor`), while the machine's flux is $\psi(i)$ from the magnetic model:
the observer-model mismatch is no longer a free parameter, it follows from the map and the
steady-state current. This module finds that current and the equivalent constant machine
there, and runs the generic analysis on it.

**What the steady state depends on.** At constant electrical speed $\omega_0$ the rotor
current is constant, so the stator equation is $u = R_s i + \omega_0 J\psi(i)$ (no
$L\,di/dt$ term): the back-EMF, and every flux an observer reconstructs, is the map's flux
at the operating current, $\omega_0 J\psi(i^*)$. The current controller holds its
reference $\hat i$ in the *estimated* frame, so the rotor current is
$i = e^{-\tilde\theta J}\hat i$; the speed loop moves $\hat i$ along the controller's own
reference path (`controller.refs`, from its constants: MTPA or $i_d$ = const, exactly what
the FOC computes) until the machine's torque $\tfrac32 n_p\,\psi(i)\times i$ (from the map)
equals the load plus friction. The steady state is the fixed point of

1. $\tilde\theta \mapsto \hat i(\tilde\theta)$: the torque reference at which
   $\tau_M(e^{-\tilde\theta J}\hat i) = \tau_L + B\,\omega_0/n_p$ (bisection; the
   reference is clipped by the controller's torque and current limits, so a load above
   what the limits give at this angle error has no solution: status `CANNOT_HOLD`);
2. $\hat i \mapsto \tilde\theta$: the principal (designed) equilibrium of the observer's
   error dynamics at $(\omega_0, \hat i)$ against the *apparent* constant machine at the
   rotor current $i^* = e^{-\tilde\theta J}\hat i$,
   $(L_d, L_q, \psi_f)_{app}$ = `magnetic.apparent_inductance(i*)`, which has the map's
   flux $\psi(i^*)$ exactly at that current.

Step 2 is exact for the equilibrium itself: an observer's error dynamics at a rest point
depend on the plant only through its flux at the rotor current there ($\psi(i^*)$, and
$R_s$), and the apparent machine reproduces it. The angle error grows with the load (the
constant model's $L_q$ exceeds the apparent one, and $\psi_f$ drops), and a larger angle
error needs more current for the same torque, which saturates the machine further: this
positive feedback is why, past some load, no fixed point exists within the current limit
and the drive loses its speed and then the lock (the closed-loop runs in
tests/test_saturated_analysis.py).

**Small-signal quantities** (stability of the equilibria, Jacobians, certificates) see
how the flux changes when the angle error moves the current along
$\partial i/\partial\tilde\theta = -J i^*$: that is the *incremental* inductance
$L_{inc}(i^*) = \partial\psi/\partial i$ (a 2 x 2 matrix with cross-saturation), not the
apparent one. A constant machine cannot carry a full $L_{inc}$ (its $\psi_q$ has no
$i_d$ term), so the stability reported here is that of the apparent machine, which is
exact for the rest point and approximate for its Jacobian. Measured for the ESO on
`ipm3k5_sat` against its error dynamics written on the map itself: the eigenvalues of
the apparent machine's Jacobian are within 0.3 % of the map's at 0.5 and 1.0 p.u. speed
and 0.5 p.u. load (slowest pair -105.0 against -104.9 1/s at 0.5 p.u.), while the
diagonal incremental machine (`incremental_plant`: $L_{dd}$, $L_{qq}$, no cross terms,
$\psi_q$ not matched) puts the slowest eigenvalue at -6.5 1/s: the apparent machine is
the better constant stand-in for both. `incremental` reports $L_{inc}$ itself.

**Checked against closed-loop simulation** (tests/test_saturated_analysis.py): the
static angle error of the ESO within 0.05 deg where the drive settles (the
parallel-model estimator's closed-loop runs on the saturated preset do not settle:
unconfirmed). Not covered: the speed loop
closes through the torque on the map, which falls as the angle error grows; this
analysis holds the current constant, so an oscillation or a loss of lock of the coupled
loop near the load limit, or a jump off a fold of the designed branch during a load
ramp, is not predicted (docs, "The analysis" in the observers guide).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp

from .._plant._magnetic import apparent_model
from .._plant._params import Drive, PMSMParams
from ..observers import AbstractObserver, OperatingPoint
from ._args import as_arrays, check_observer
from ._equilibria import Equilibria
from ._generic import STATUS_DEGENERATE, STATUS_NONE, equilibria_traced


#: `SaturatedPoint.verdict` codes: as the feasibility maps (0 feasible, 1 infeasible, 2
#: no equilibrium, -1 degenerate), plus 3: the controller cannot deliver the load torque
#: within its limits at the angle error the observer would settle to (no fixed point;
#: the drive cannot hold the operating point and loses its speed).
VERDICT_FEASIBLE, VERDICT_INFEASIBLE, VERDICT_NONE, VERDICT_DEGENERATE = 0, 1, 2, -1
VERDICT_CANNOT_HOLD = 3
VERDICTS = {0: "feasible", 1: "infeasible", 2: "no equilibrium", -1: "degenerate",
            3: "cannot hold"}


class SaturatedPoint(eqx.Module):
    """The steady state of a sensorless drive on a saturated machine at one operating
    point (any batch shape in front).

    - `w_m`: electrical speed (rad/s); `tau_L`: load torque (N m).
    - `theta`: the static angle error (rad, true minus estimate): the principal
      equilibrium of the observer's error dynamics at the fixed point.
    - `i_ref`: the controller's current in its (estimated) frame (A, `(..., 2)`): the
      `OperatingPoint` current of the analysis.
    - `i_dq`: the rotor current, $e^{-\\tilde\\theta J}$ `i_ref` (A, `(..., 2)`).
    - `tau_ref`: the speed loop's torque reference (N m).
    - `apparent`: `(L_d, L_q, psi_f)` (H, H, V s) of the machine at `i_dq`
      (`magnetic.apparent_inductance`): the constant plant of the static analysis.
    - `incremental`: $\\partial\\psi/\\partial i$ at `i_dq` (H, `(..., 2, 2)`).
    - `equilibria`: every equilibrium at the fixed point (`Equilibria`, on the apparent
      plant).
    - `stable`: the principal equilibrium is stable.
    - `verdict`: `VERDICTS` code (0 feasible: the principal equilibrium is the only
      stable one; 1 infeasible: it is unstable or another one is stable; 2 no
      equilibrium; -1 degenerate; 3 cannot hold: no fixed point within the limits).
    - `converged`: the fixed-point iteration settled (change of the angle error below
      1e-6 rad at its last step).
    """

    w_m: jnp.ndarray
    tau_L: jnp.ndarray
    theta: jnp.ndarray
    i_ref: jnp.ndarray
    i_dq: jnp.ndarray
    tau_ref: jnp.ndarray
    apparent: tuple
    incremental: jnp.ndarray
    equilibria: Equilibria
    stable: jnp.ndarray
    verdict: jnp.ndarray
    converged: jnp.ndarray


def _rot(i, th):
    """`e^{th J} i` (rotation of a dq vector by `th`, rad)."""
    c, s = jnp.cos(th), jnp.sin(th)
    return jnp.stack([c * i[0] - s * i[1], s * i[0] + c * i[1]])


def constant_plant(plant: PMSMParams, L_d, L_q, psi_f) -> PMSMParams:
    """`plant` as a constant-inductance machine with `L_d`, `L_q` (H) and `psi_f` (V s)
    (its magnetic model dropped, everything else kept)."""
    return PMSMParams(R_s=plant.R_s, L_d=L_d, L_q=L_q, psi_f=psi_f, n_p=plant.n_p,
                      harmonics=plant.harmonics, magnetic=None)


def apparent_plant(plant: PMSMParams, i_dq) -> PMSMParams:
    """The constant machine with the apparent inductances and PM flux of the saturated
    `plant` at the rotor current `i_dq` (A, `(2,)`): the same flux as the map there."""
    return apparent_model(plant, plant.magnetic, i_dq)


def incremental_plant(plant: PMSMParams, i_dq) -> PMSMParams:
    r"""The constant machine with the diagonal incremental inductances $L_{dd}$, $L_{qq}$
    of the saturated `plant` at `i_dq` (A) and the PM flux that gives the map's $\psi_d$
    there ($\psi_d - L_{dd} i_d$); its $\psi_q$ differs from the map's unless the map is
    linear in $i_q$ (module docstring)."""
    i_dq = jnp.asarray(i_dq)
    psi_d, _, l_dd, _, _, l_qq = plant.magnetic.flux_and_inductance(i_dq[0], i_dq[1])
    return constant_plant(plant, l_dd, l_qq, psi_d - l_dd * i_dq[0])


def _check_saturated(owner, drive):
    if not isinstance(drive, Drive):
        raise ValueError(f"`{owner}(drive=...)` must be a `Drive` (e.g. "
                         f"`pj.preset('ipm3k5_sat')`); got {type(drive).__name__}.")
    if drive.three_phase_motor.magnetic is None:
        raise ValueError(f"`{owner}(drive=...)`: {drive.name!r} has no magnetic model "
                         "(`PMSMParams.magnetic` is None); the saturated analysis needs a "
                         "saturated machine, e.g. `pj.preset('ipm3k5_sat')` (a constant "
                         "machine's mismatch is a free parameter: `observer.with_motor`).")


def saturated_operating_point(observer: AbstractObserver, drive: Drive, w_m, tau_L, *,
                              controller=None, n_outer: int = 16, n_bisect: int = 48,
                              **equilibria_options) -> SaturatedPoint:
    r"""The steady state of the sensorless drive `drive` (saturated machine) with
    `observer` (its constant model) at electrical speed `w_m` (rad/s) and load torque
    `tau_L` (N m): the current on the controller's reference path, the static angle
    error, the equivalent plant there (apparent and incremental) and the verdict
    (`SaturatedPoint`; derivation in the module docstring).

    **Arguments:**

    - `observer`: any `AbstractObserver` (its `motor` is the model it deploys).
    - `drive`: a `Drive` whose machine has a magnetic model (`PMSMParams.magnetic`).
    - `w_m`: electrical speed (rad/s), nonzero; `tau_L`: load torque (N m), any sign.
    - `controller`: the `FOC` whose reference path (`controller.refs` on its own machine
      model, clipped at `controller.speed.tau_max` and the current limit) sets the
      current; default `FOC.from_drive(drive)` (i_d = 0, as `pmsmjax simulate`).
    - `n_outer`: fixed-point iterations; `n_bisect`: bisection steps of the torque
      balance.
    - `equilibria_options`: passed to the equilibria (`equilibria_traced`), e.g.
      `method="generic"`, `n_grid`.

    Pure and vmappable over `w_m` and `tau_L` (wrap it in `jax.vmap`; see
    `saturated_map`).
    """
    check_observer("saturated_operating_point", observer)
    _check_saturated("saturated_operating_point", drive)
    if controller is None:
        from .._control._foc import FOC

        controller = FOC.from_drive(drive)
    dtype = jnp.result_type(w_m, tau_L, float)
    obs = as_arrays(observer, dtype, ints=False)
    plant = as_arrays(drive.three_phase_motor, dtype, ints=False)
    ctrl = as_arrays(controller, dtype, ints=False)
    mech = as_arrays(drive.mechanics, dtype)
    return _point(obs, plant, ctrl, mech, jnp.asarray(w_m, dtype), jnp.asarray(tau_L, dtype),
                  n_outer, n_bisect, equilibria_options)


def _saturated_point(obs, plant, ctrl, mech, w_m, tau_L, n_outer, n_bisect, options):
    mag = plant.magnetic
    # the generic route's Newton starts where two branches show, as `equilibria` (a point
    # of the steady-state analysis is one equilibria call per outer iteration)
    starts = {"n_starts": options.get("n_grid", 64), **options}
    tau_need = tau_L + mech.B * w_m / plant.n_p
    tau_max = ctrl.speed.tau_max
    k_tau = 1.5 * plant.n_p

    def refs(tau_ref):
        return ctrl.refs(tau_ref, ctrl.current.motor, ctrl.k_tau, w=w_m,
                         u_max=ctrl.current.u_max)

    def torque(tau_ref, th):
        i = _rot(refs(tau_ref), -th)
        psi = mag.flux_dq(i)
        return k_tau * (psi[0] * i[1] - psi[1] * i[0])

    def balance(th):
        # bisection of torque(tau_ref) = tau_need on [-tau_max, tau_max]: the torque
        # grows with the reference along the path (it is flat where the current limit
        # clips it); `hold` says whether the limits reach the load at all
        lo, hi = -tau_max, tau_max
        f_lo, f_hi = torque(lo, th) - tau_need, torque(hi, th) - tau_need
        hold = (f_lo <= 0) & (f_hi >= 0)

        def body(c, _):
            a, b = c
            m = 0.5 * (a + b)
            up = torque(m, th) - tau_need < 0
            return (jnp.where(up, m, a), jnp.where(up, b, m)), None

        (a, b), _ = jax.lax.scan(body, (lo, hi), None, length=n_bisect)
        return 0.5 * (a + b), hold

    def analyse(th):
        tau_ref, hold = balance(th)
        i_ref = refs(tau_ref)
        i_dq = _rot(i_ref, -th)
        eq = equilibria_traced(obs, apparent_model(plant, mag, i_dq),
                               OperatingPoint(w_m, i_ref), **starts)
        return eq, tau_ref, hold, i_ref, i_dq

    def step(c, _):
        # secant steps on h(th) = Theta(th) - th (the plain iteration th <- Theta(th)
        # contracts slowly near the load where the fixed point disappears), bounded to
        # 0.2 rad a step; where the limits cannot deliver the torque at th, back half way
        # to the previous iterate. One trace of the analysis for the whole iteration
        # (its last step is the one reported): the compile time is that of one
        # equilibria call.
        th_prev, h_prev, th, first = c
        eq, tau_ref, hold, i_ref, i_dq = analyse(th)
        ok = (eq.n > 0) & hold
        h = jnp.where(ok, eq.theta[eq.principal] - th, jnp.nan)
        den = h - h_prev
        use = ~first & jnp.isfinite(den) & (jnp.abs(den) > 1e-12)
        sec = th - h * (th - th_prev) / jnp.where(use, den, 1.0)
        th_new = jnp.where(use, sec, th + h)
        th_new = th + jnp.clip(th_new - th, -0.2, 0.2)
        th_new = jnp.where(ok, th_new, 0.5 * (th + th_prev))
        keep = ok & (jnp.abs(h) < 1e-10)  # settled: stay (no 0/0 secant)
        th_new = jnp.clip(jnp.where(keep, th, th_new), -0.5 * math.pi, 0.5 * math.pi)
        new = (jnp.where(ok, th, th_prev), jnp.where(ok, h, h_prev), th_new,
               jnp.asarray(False) & first)
        return new, (th, eq, tau_ref, hold, i_ref, i_dq)

    th0 = jnp.zeros_like(w_m)
    c0 = (th0, jnp.asarray(jnp.nan, th0.dtype), th0, jnp.asarray(True))
    _, outs = jax.lax.scan(step, c0, None, length=n_outer + 1)
    th, eq, tau_ref, hold, i_ref, i_dq = jax.tree_util.tree_map(lambda a: a[-1], outs)
    k = eq.principal
    th_eq = eq.theta[k]
    converged = (eq.n > 0) & hold & (jnp.abs(th_eq - th) < 1e-6)
    stable = eq.stable[k] & (eq.n > 0)
    others = jnp.any(eq.stable & (jnp.arange(eq.stable.shape[-1]) != k))
    verdict = jnp.where(
        eq.status == STATUS_DEGENERATE, VERDICT_DEGENERATE,
        jnp.where(eq.status == STATUS_NONE, VERDICT_NONE,
                  jnp.where(~hold | ~converged, VERDICT_CANNOT_HOLD,
                            jnp.where(stable & ~others, VERDICT_FEASIBLE,
                                      VERDICT_INFEASIBLE)))).astype(jnp.int32)
    return SaturatedPoint(
        w_m=w_m, tau_L=tau_L, theta=jnp.where(converged, th_eq, jnp.nan), i_ref=i_ref,
        i_dq=i_dq, tau_ref=tau_ref, apparent=mag.apparent_inductance(i_dq),
        incremental=mag.incremental_inductance(i_dq), equilibria=eq, stable=stable,
        verdict=verdict, converged=converged)


_point = eqx.filter_jit(_saturated_point)


@eqx.filter_jit
def _map(obs, plant, ctrl, mech, W, T, n_outer, n_bisect, options):
    f = lambda w, t: _saturated_point(obs, plant, ctrl, mech, w, t, n_outer,  # noqa: E731
                                      n_bisect, options)
    return jax.vmap(f)(W.ravel(), T.ravel())


def saturated_map(observer: AbstractObserver, drive: Drive, speeds, loads, *,
                  controller=None, n_outer: int = 16, n_bisect: int = 48,
                  **equilibria_options) -> SaturatedPoint:
    """`saturated_operating_point` over the grid `speeds` x `loads` (electrical rad/s x
    N m, 1-D each), vmapped and compiled once: a `SaturatedPoint` whose arrays have
    the leading shape `(len(speeds), len(loads))`. Its `theta` is the map of the static
    angle error (rad, NaN where the drive cannot hold the point) and `verdict` the
    feasibility verdict per point (`VERDICTS`). Plot it with
    `pmsmjax.plotting.plot_saturated_map`."""
    check_observer("saturated_map", observer)
    _check_saturated("saturated_map", drive)
    if controller is None:
        from .._control._foc import FOC

        controller = FOC.from_drive(drive)
    speeds, loads = jnp.atleast_1d(jnp.asarray(speeds)), jnp.atleast_1d(jnp.asarray(loads))
    if speeds.ndim != 1 or loads.ndim != 1:
        raise ValueError(f"`saturated_map(speeds=..., loads=...)` must be 1-D; got shapes "
                         f"{speeds.shape} and {loads.shape}.")
    if not bool(jnp.all(speeds != 0)):
        raise ValueError("`saturated_map(speeds=...)`: every speed must be nonzero (rad/s, "
                         "electrical): at standstill the observers' error dynamics have "
                         "no isolated rest point.")
    dtype = jnp.result_type(speeds, loads, float)
    W, T = jnp.meshgrid(speeds.astype(dtype), loads.astype(dtype), indexing="ij")
    out = _map(as_arrays(observer, dtype, ints=False),
               as_arrays(drive.three_phase_motor, dtype, ints=False),
               as_arrays(controller, dtype, ints=False), as_arrays(drive.mechanics, dtype),
               W, T, n_outer, n_bisect, equilibria_options)
    return jax.tree_util.tree_map(lambda a: a.reshape(W.shape + a.shape[1:]), out)


def describe_mismatch(observer: AbstractObserver, point: SaturatedPoint) -> str:
    """One line: the mismatch that follows from the map at `point` (a single point): the
    observer's constants against the apparent (static) and incremental (small-signal)
    machine at the steady-state current."""
    m = observer.motor
    L_d, L_q, psi_f = (float(v) for v in point.apparent)
    Li = jnp.asarray(point.incremental)
    i = [float(v) for v in point.i_dq]
    th = float(point.theta)
    th_txt = "no steady state" if math.isnan(th) else f"angle error {math.degrees(th):.3g} deg"
    return (f"saturated plant: mismatch from the map at i_dq = ({i[0]:.3g}, {i[1]:.3g}) A "
            f"({th_txt}): apparent L_d {L_d * 1e3:.4g} mH, L_q {L_q * 1e3:.4g} mH, psi_f "
            f"{psi_f:.4g} V s (observer {float(m.L_d) * 1e3:.4g} mH, "
            f"{float(m.L_q) * 1e3:.4g} mH, {float(m.psi_f):.4g} V s); incremental L_dd "
            f"{float(Li[0, 0]) * 1e3:.4g} mH, L_qq {float(Li[1, 1]) * 1e3:.4g} mH, L_dq "
            f"{float(Li[0, 1]) * 1e3:.4g} mH")
