r"""Harmonic sensitivity of any observer: the angle-error ripple a back-EMF harmonic causes.

**The disturbance.** A PM-flux harmonic of signed order $h$ (`EMFHarmonics`: positive
= rotating with the rotor) adds to the stator voltage, in rotor coordinates, the
back-EMF

$$e_{h,dq}(t) = a_h\,\psi_f\,\omega\,\mathrm{sgn}(h)\,J\,e^{((h-1)\theta(t) + \phi_h)J}
[1, 0]^T,\qquad \theta(t) = \omega t,$$

a real 2-vector of constant length $E = a_h\psi_f|\omega|$ that turns at
$\Omega = (h-1)\,\omega$ in the rotor frame. With ideal current control (the current held
at $i_0$ in the observer's estimated frame, as in every `OperatingPoint`) the current
does not see it, but the measured voltage carries it: to the observer it is a voltage
$d(t)$ that its model does not explain.

**Linearisation.** About the designed equilibrium $x_0$ (`observer.designed_error`) the
error dynamics with that disturbance are $\dot x = Ax + Bd$, $A = \partial f/\partial x$
(`linearization`, from `error_rhs`) and $B = \partial f/\partial d$ (`(n, 2)`, V
rotor-frame input). The contract's `error_rhs` has no voltage input, so $B$ is taken
from the observer's own `step` (the code that runs), through the same maps as
`discrete_error_map`: one step of length $\tau$ with $d$ added to the measured voltage
has $\partial x_{k+1}/\partial d = \tau B + O(\tau^2)$; two steps ($\tau$, $2\tau$,
$\tau\rho = 10^{-3}$ with $\rho$ the larger of $|\omega|$ and the row-sum norm of the
scaled $A$) and Richardson extrapolation give $B$ to $O(\tau^2)$. Forward-mode
derivatives of a linear input suffer no cancellation, so this holds in float32 too.

**Steady-state ripple** (derivation). Write the rotating disturbance as
$d(t) = E\,(\cos\Omega t\, d_0 + \sin\Omega t\, J d_0) = E\,\mathrm{Re}\{(d_0 - jJd_0)
e^{j\Omega t}\}$ with a unit vector $d_0 = e^{\phi J}[1,0]^T$. Since
$J[1,-j]^T = j[1,-j]^T$, $d_0 - jJd_0 = e^{j\phi}v$ with $v = [1, -j]^T$: the phase
only shifts time. The forced response of the (Hurwitz) linear system is
$x(t) = E\,\mathrm{Re}\{(j\Omega I - A)^{-1}Bv\,e^{j(\Omega t + \phi)}\}$, so the angle
error $\tilde\theta = c^Tx$ ($c$ the angle coordinate) oscillates with peak

$$\hat{\tilde\theta}_h = E\,\left|c^T(j\Omega I - A)^{-1}B\,[1, -j]^T\right|.$$

$B$ is a real $n\times 2$ matrix, not a complex scalar gain, so the two directions of
rotation differ: with $G(s) = c^T(sI-A)^{-1}B$ (1 x 2), $\Omega < 0$ gives
$|G(j|\Omega|)[1, +j]^T|$. $[1,\mp j]$ pick the parts of $G$ that respond to the
positive and the negative rotating components: both $+(h-1)\omega$ and $-(h-1)\omega$
components of $G$ enter, and orders $h$ and $2-h$ (e.g. $7$ and $-5$) give different
ripple unless $B$ and $A$ commute with $J$.

**Order 1** ($\Omega = 0$): the "harmonic" is a 1 % error of the fundamental, i.e. a
1 % PM-flux error (the plant's $\psi_f$ 1 % above the observer's): the constant
$d = 0.01\,\psi_f\,\omega J[1,0]^T$, and the result is the static angle offset
$|c^TA^{-1}Bd|$ (its phase is fixed, so it is not the rotating formula at
$\Omega = 0$).

**Angle-dependent observers** (the rotor-flux observer applies gains per
stationary-frame component: its linearisation $A(\theta)$ has a $4\theta$ term). Without
`op.theta` the continuous result is a *harmonic balance* of the periodic linearisation
(what a Floquet treatment gives for a periodic input): $A(\theta)$ (`error_rhs` at
`OperatingPoint.theta`) and $B(\theta)$ at 16 rotor angles give their Fourier
coefficients $A_m$, $B_m$ ($|m| \le 6$; $A_0$ is `error_rhs`'s own average), and the
response to $v e^{j\Omega t}$ with $\theta = \omega t$ is
$x = \sum_{|k| \le 8} X_k e^{j(\Omega + k\omega)t}$ with
$j(\Omega + k\omega)X_k - \sum_m A_m X_{k-m} = B_k v$. The harmonic now also drives
sidebands at $\Omega + k\omega$ (for the rotor-flux observer at $\Omega \pm 4\omega$;
where such a sideband falls on another order's frequency the two add), and the peak
depends on the harmonic's phase relative to the rotor: the result is the worst case over
that phase, $E\max_\theta|\sum_k c^TX_k e^{jk\theta}|$ (256 angles). For an observer
whose error dynamics do not depend on the angle every $A_m, B_m$ with $m \ne 0$ vanish
and this is the formula above: an observer that does not declare `angle_dependent`
(every one but the rotor-flux observer) is evaluated at one angle, and the balance
reduces to it. With `op.theta` the linearisation is frozen at that
angle. The discrete variant uses the angle-averaged step (the component at $\Omega$
only, no sidebands).

**Discrete variant** (`T_s` given): $x_{k+1} = \Phi x_k + \Gamma d_k$ from one real
step at the sampling period ($\Phi$, $\Gamma$ as above, averaged over 16 angles, or
at one angle for an observer that is not `angle_dependent`), the
disturbance held over each period as its period average (factor
$\mathrm{sinc}(h\omega T_s/2)$ at mid-period), evaluated at $z = e^{j\Omega T_s}$:
$E\,|c^T(zI-\Phi)^{-1}\Gamma v|\,\mathrm{sinc}$ (the amplitude of the sampled ripple).

**Standstill**: no back-EMF, so no harmonic: the ripple is 0 there (exactly, and with a
zero gradient). The steady-state ripple only means something where the linearisation is
stable (check `analysis.stability(linearization(...))`); where $j\Omega$ is an eigenvalue
of $A$ it is `inf`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._frames import rotate
from .._plant._params import Drive
from .._sim._batching import values_as_arrays, without_labels
from ..observers import AbstractObserver, Measurement, OperatingPoint, PlantPoint
from ._args import check_observer
from ._discrete import _true_flux_ab


_N_ANGLES = 16


def _step_input_jacobians(observer, plant, op, x0, T_s, theta_k, dtype):
    """`(Phi, Gamma)`: the Jacobians of one real step of length `T_s` (error
    coordinates at t_{k+1}) with respect to the error coordinates at t_k and to a
    rotor-frame voltage `d` (V, `(2,)`) added to the measured voltage over the period
    (applied in the stationary frame at the mid-period rotor angle)."""
    a = observer.coordinates.angle
    i0 = op.i_dq.astype(dtype)
    w = op.w_m.astype(dtype)
    nan = jnp.full((), jnp.nan, dtype)

    def fn(x, d):
        th0 = jnp.asarray(theta_k, dtype)
        th1 = th0 + w * T_s
        i_k = rotate(i0, th0 - x[a])
        truth0 = PlantPoint(theta=th0, w_m=w, i_ab=i_k)
        state = observer.observer_state(x, truth0, plant)
        psi0 = _true_flux_ab(plant, th0, i_k)
        d_ab = rotate(d, th0 + 0.5 * w * T_s)

        # ideal current control in the estimated frame: the sampled current at t_{k+1}
        # follows the new estimate (a fixed point, 3 iterations in one traced step)
        def iterate(i_next, _):
            u = (_true_flux_ab(plant, th1, i_next) - psi0) / T_s \
                + 0.5 * plant.R_s * (i_k + i_next) + d_ab
            new, est = observer.step(state, Measurement(i_ab=i_next, u_ab=u, theta=nan,
                                                        w_m=nan), T_s)
            return rotate(i0, est.theta_hat).astype(dtype), (new, i_next)

        _, (news, i_used) = jax.lax.scan(iterate, rotate(i0, th1 - x[a]), None, length=3)
        new = jax.tree_util.tree_map(lambda v: v[-1], news)
        return observer.error_state(new, PlantPoint(theta=th1, w_m=w, i_ab=i_used[-1]),
                                    plant)

    return jax.jacfwd(fn, argnums=(0, 1))(x0, jnp.zeros(2, dtype))


def _angles(observer, op, dtype):
    """The rotor angles at which the linearisation is evaluated: `op.theta` if given,
    else 16 angles over a turn for an observer whose error dynamics depend on the angle
    (`angle_dependent`), else one (they are the same at every angle)."""
    if op.theta is not None:
        return jnp.asarray(op.theta, dtype)[None]
    if not observer.angle_dependent:
        return jnp.zeros((1,), dtype)
    return 2 * jnp.pi * jnp.arange(_N_ANGLES, dtype=dtype) / _N_ANGLES


def _jacobian_grid(observer, plant, op, x0, T_s, dtype):
    """`(Phi, Gamma)` at each rotor angle (`_angles`) for each of the step lengths `T_s`
    (`(m,)`): `(m, M, n, n)`, `(m, M, n, 2)` (one traced step for all)."""
    th = _angles(observer, op, dtype)
    T = jnp.asarray(T_s, dtype).reshape(-1)
    TT, HH = jnp.broadcast_arrays(T[:, None], th[None, :])
    Phi, Gam = jax.vmap(lambda t, h: _step_input_jacobians(observer, plant, op, x0, t, h,
                                                           dtype))(TT.ravel(), HH.ravel())
    m, k = TT.shape
    return Phi.reshape(m, k, *Phi.shape[1:]), Gam.reshape(m, k, *Gam.shape[1:])


def _averaged_jacobians(observer, plant, op, x0, T_s, dtype):
    """`(Phi, Gamma)` averaged over the rotor angle: `(m, n, n)`, `(m, n, 2)`."""
    Phi, Gam = _jacobian_grid(observer, plant, op, x0, T_s, dtype)
    return jnp.mean(Phi, 1), jnp.mean(Gam, 1)


def _input_matrices(observer, plant, op, x0, dtype):
    """`(A(theta), B(theta), A)`: at each rotor angle of `_angles` (`(M, n, n)`,
    `(M, n, 2)`), `A` from `error_rhs` at that angle and `B` by Richardson extrapolation
    of the step's input Jacobian; and `A` of `error_rhs` at `op` itself (its average
    over the angle without `op.theta`)."""
    th = _angles(observer, op, dtype)
    A = jax.vmap(lambda t: jax.jacfwd(lambda v: observer.error_rhs(
        v, OperatingPoint(op.w_m, op.i_dq, t), plant))(x0))(th)
    A_avg = jax.jacfwd(lambda v: observer.error_rhs(v, op, plant))(x0)
    scale = jnp.asarray(observer.error_scale(op, plant), dtype)
    A_s = A_avg * scale[None, :] / scale[:, None]
    rho = jnp.maximum(jnp.abs(op.w_m).astype(dtype), jnp.max(jnp.sum(jnp.abs(A_s), 1)))
    rho = jnp.where(jnp.isfinite(rho) & (rho > 0), rho, 1.0)
    tau = 1e-3 / rho
    _, G = _jacobian_grid(observer, plant, op, x0, jnp.stack([tau, 2 * tau]), dtype)
    B = (2.0 * G[0] / tau - G[1] / (2 * tau)).astype(dtype)
    return A, B, A_avg


def input_matrix(observer: AbstractObserver, drive: Drive, op: OperatingPoint, x=None):
    r"""$B = \partial f/\partial d$ (`(n, 2)`, SI: coordinate units per second per V):
    how a rotor-frame voltage $d$ that the observer's model does not explain (added to
    the measured stator voltage) enters the continuous error dynamics at `op`, about `x`
    (default: the designed equilibrium). From the observer's own step by Richardson
    extrapolation (module docstring); averaged over the rotor angle unless `op.theta`
    is given. Returns `(B, A)` with `A` = `linearization` at the same point."""
    plant = drive.three_phase_motor
    dtype = jnp.result_type(op.w_m, float)
    x0 = (jnp.asarray(observer.designed_error(op, plant), dtype) if x is None
          else jnp.asarray(x, dtype))
    _, B, A = _input_matrices(observer, plant, op, x0, dtype)
    return jnp.mean(B, 0), A


_K_COEF = 6  # Fourier coefficients of the periodic linearisation used (16 angles)
_K_SIDE = 8  # sidebands kept in the harmonic balance
_N_PEAK = 256  # angle grid on which the peak of the periodic response is taken


def _balance_peak(A_k, B_k, Om, w, a, u, real_input):
    r"""Harmonic balance of $\dot x = A(\theta)x + B(\theta)u e^{j\Omega t}$,
    $\theta = \omega t$, with $A, B$ given by their Fourier coefficients `A_k`, `B_k`
    (`(2K_c+1, ...)`, k = -K_c..K_c, or one: time-invariant): the response is
    $x = \sum_k X_k e^{j(\Omega + k\omega)t}$; returns the peak over one period of
    $|\sum_k X_{k,a} e^{jk\theta}|$ (the worst case over the input's phase), or of
    its real part for a real input (`real_input`: a fixed phase)."""
    kc = (A_k.shape[0] - 1) // 2
    K = _K_SIDE if kc > 0 else 0
    n = A_k.shape[-1]
    ks = jnp.arange(-K, K + 1)
    eye = jnp.eye(n, dtype=A_k.dtype)
    rows = []
    for i in range(2 * K + 1):
        blocks = []
        for j in range(2 * K + 1):
            m = i - j  # X_j feeds row i through A_{i-j}
            blk = -A_k[m + kc] if abs(m) <= kc else jnp.zeros((n, n), A_k.dtype)
            if i == j:
                blk = blk + 1j * (Om + ks[i] * w) * eye
            blocks.append(blk)
        rows.append(jnp.concatenate(blocks, 1))
    M = jnp.concatenate(rows, 0)
    rhs = jnp.concatenate([B_k[k + kc] @ u if abs(k) <= kc else jnp.zeros(n, A_k.dtype)
                           for k in range(-K, K + 1)])
    X = jnp.linalg.solve(M, rhs).reshape(2 * K + 1, n)
    Y = X[:, a]
    if K == 0:
        return jnp.where(real_input, jnp.abs(jnp.real(Y[0])), jnp.abs(Y[0]))
    th = 2 * jnp.pi * jnp.arange(_N_PEAK) / _N_PEAK
    y = jnp.exp(1j * th[:, None] * ks[None, :].astype(th.dtype)) @ Y
    return jnp.where(real_input, jnp.max(jnp.abs(jnp.real(y))), jnp.max(jnp.abs(y)))


def harmonic_ripple(observer: AbstractObserver, drive: Drive, op: OperatingPoint, orders,
                    *, T_s=None):
    r"""Peak angle-error ripple (deg) per 1 % back-EMF harmonic of each signed order.

    **Arguments:**

    - `observer`: any sensorless `AbstractObserver` (its `motor` is its model).
    - `drive`: the plant's `Drive` (its `three_phase_motor` is the true machine; its
      $\psi_f$ sets the fundamental back-EMF $\psi_f|\omega|$).
    - `op`: the `OperatingPoint` (electrical speed `w_m` in rad/s, current `i_dq` in A
      in the estimated frame, optional rotor angle `theta` in rad for angle-dependent
      observers). May be batched by `jax.vmap`.
    - `orders`: signed harmonic orders (ints, e.g. `(1, -5, 7, -17, 19)`): a harmonic of
      order $h$ appears at $(h-1)\omega$ in the rotor frame; order 1 is a 1 % error of
      the fundamental (a 1 % PM-flux error; static offset), 0 is not allowed.
    - `T_s`: None (default) for the continuous-time linearisation; a sampling period
      (s) for the discrete observer at that period.

    **Returns:** `(len(orders),)` array: the peak of the steady-state angle error
    $\tilde\theta$ (deg) for a harmonic of amplitude 1 % of the fundamental back-EMF,
    from the linearisation about the designed equilibrium (see the module docstring for
    the derivation); for an observer with angle-dependent error dynamics the worst case
    over the harmonic's phase, sidebands included. 0 at standstill (no back-EMF); `inf`
    where $j\Omega$ is an eigenvalue. Meaningful where the linearisation is stable
    (`analysis.stability(analysis.linearization(...))`). Pure: jit it and `jax.vmap` it
    over operating points (and designs); float32 works. This signature is stable.
    """
    check_observer("harmonic_ripple", observer)
    if not isinstance(drive, Drive):
        raise ValueError(f"`harmonic_ripple(drive=...)` must be a `Drive` (e.g. "
                         f"`pj.preset('zhang750')`); got {type(drive).__name__}.")
    if not isinstance(op, OperatingPoint):
        raise ValueError(f"`harmonic_ripple(op=...)` must be an `analysis.OperatingPoint`; "
                         f"got {type(op).__name__}.")
    h = jnp.asarray(orders)
    if h.ndim != 1 or h.shape[0] == 0:
        raise ValueError(f"`harmonic_ripple(orders=...)` must be a non-empty sequence of "
                         f"signed orders; got {orders!r}.")
    try:
        concrete = [int(v) for v in jax.device_get(h)]
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError,
            TypeError):
        concrete = None
    if concrete is not None and 0 in concrete:
        raise ValueError(f"`harmonic_ripple(orders=...)`: order 0 is not a harmonic (a "
                         f"constant flux has no back-EMF); got {tuple(concrete)}.")
    if T_s is not None and not float(T_s) > 0:
        raise ValueError(f"`harmonic_ripple(T_s=...)` must be a positive sampling period "
                         f"(s) or None; got {T_s!r}.")
    # the observer's and drive's Python floats as traced values: another design or
    # machine runs the compiled program again (pmsmjax._sim._batching.values_as_arrays)
    dtype = jnp.result_type(op.w_m, op.i_dq, float)
    observer, drive = values_as_arrays((observer, without_labels(drive)), dtype)
    return _harmonic_ripple(observer, drive, op, h, None if T_s is None else float(T_s))


@eqx.filter_jit
def _harmonic_ripple(observer, drive, op, h, T_s):
    plant = drive.three_phase_motor
    dtype = jnp.result_type(op.w_m, op.i_dq, float)
    w = jnp.asarray(op.w_m, dtype)
    # at standstill the ripple is 0; evaluate the linearisation at a regular speed there
    moving = w != 0
    w_ev = jnp.where(moving, w, jnp.asarray(drive.w_rated, dtype))
    op_ev = OperatingPoint(w_ev, op.i_dq.astype(dtype), op.theta)
    a = observer.coordinates.angle
    hf = h.astype(dtype)
    Omega = (hf - 1.0) * w_ev
    E = 0.01 * jnp.asarray(plant.psi_f, dtype) * jnp.abs(w_ev)
    ctype = jnp.result_type(dtype, jnp.complex64)
    v = jnp.array([1.0, -1.0j], ctype)
    d1 = jnp.stack([jnp.zeros((), dtype), jnp.sign(w_ev)]).astype(ctype)  # order 1
    n = observer.coordinates.n
    eye = jnp.eye(n, dtype=ctype)
    if T_s is None:
        x0 = jnp.asarray(observer.designed_error(op_ev, plant), dtype)
        A_th, B_th, A_avg = _input_matrices(observer, plant, op_ev, x0, dtype)
        if op.theta is None and observer.angle_dependent:
            # Fourier coefficients of the periodic A(theta), B(theta) (k = -6..6 from 16
            # angles; the average A from error_rhs itself), harmonic balance with
            # sidebands k = -8..8
            th = _angles(observer, op_ev, dtype)
            ks = jnp.arange(-_K_COEF, _K_COEF + 1)
            ph = jnp.exp(-1j * ks[:, None] * th[None, :]).astype(ctype)  # (2Kc+1, M)
            A_k = jnp.einsum("km,mij->kij", ph, A_th.astype(ctype)) / th.shape[0]
            A_k = A_k.at[_K_COEF].set(A_avg.astype(ctype))
            B_k = jnp.einsum("km,mij->kij", ph, B_th.astype(ctype)) / th.shape[0]
        else:
            A_k = A_avg.astype(ctype)[None]
            B_k = B_th.astype(ctype)
        amp = jax.vmap(lambda Om, is_one: _balance_peak(A_k, B_k, Om, w_ev, a,
                                                        jnp.where(is_one, d1, v), is_one)
                       )(Omega, h == 1)
    else:
        T = jnp.asarray(T_s, dtype)
        x0 = jnp.asarray(observer.designed_error(op_ev, plant), dtype)
        Phi, Gam = _averaged_jacobians(observer, plant, op_ev, x0, T, dtype)
        Phi, Gam = Phi[0].astype(ctype), Gam[0].astype(ctype)

        def one(Om, hh, is_one):
            z = jnp.exp(1j * Om * T)
            sinc = jnp.sinc(0.5 * hh * w_ev * T / jnp.pi)  # sin(x)/x at x = h w T_s / 2
            X = jnp.linalg.solve(z * eye - Phi, Gam @ jnp.where(is_one, d1, v)
                                 * jnp.exp(0.5j * Om * T))
            return jnp.abs(X[a]) * jnp.abs(sinc)

        amp = jax.vmap(one)(Omega, hf, h == 1)
    deg = jnp.degrees(E * amp).astype(dtype)
    deg = jnp.where(jnp.isnan(deg), jnp.inf, deg)
    return jnp.where(moving, deg, jnp.zeros_like(deg))
