r"""Reduced-order flux observer in estimated rotor coordinates, with speed adaptation and
optional PM-flux adaptation.

References: M. Hinkkanen, S. E. Saarakkala, H. A. A. Awan, E. Mölsä, T. Tuovinen,
"Observers for sensorless synchronous motor drives: framework for design and analysis",
IEEE Trans. Ind. Appl. 54(6), 2018, doi:10.1109/TIA.2018.2858753 (the observer and its
gains); T. Tuovinen, H. A. A. Awan, J. Kukkola, S. E. Saarakkala, M. Hinkkanen,
"Permanent-magnet flux adaptation for sensorless synchronous motor drives", IEEE SLED
2018 (the PM-flux adaptation).

**Equations** (complex notation $x = x_d + jx_q$ in the estimated rotor frame at angle
$\hat\theta$, stored as real 2-vectors; model quantities are the observer's `motor`):

$$\psi_s(i) = L_d i_d + \hat\psi_f + jL_q i_q,\qquad e = \psi_s(i) - \hat\psi,\qquad
\psi_a = \psi_s(i) - L_q i_d - jL_d i_q = \hat\psi_f + (L_d - L_q)(i_d - ji_q),$$

$$\varepsilon = -\mathrm{Im}\{e/\psi_a\},\qquad \omega_c = \hat\omega + k_\theta\varepsilon,$$

$$\frac{d\hat\psi}{dt} = u - R_s i - j\omega_c\hat\psi + k_1 e + k_2 e^*,\qquad
\frac{d\hat\theta}{dt} = \omega_c,\qquad \frac{d\hat\omega}{dt} = k_\omega\varepsilon,$$

with the sensorless gain $k_2 = k_1\psi_a/\psi_a^*$, so that $k_1 e + k_2 e^* =
2k_1\psi_a\mathrm{Re}\{e/\psi_a\}$: the flux is corrected only along $\psi_a$, the
perpendicular direction through the angle (the observer's order is reduced by one), and
$k_1 = \sigma_0 + \zeta_\infty|\hat\omega|$, $k_\theta = 2\alpha_o$, $k_\omega = \alpha_o^2$.

*Why these signs* (derived here; matched model, small errors). In the estimated frame the
true flux is $\psi = e^{j\tilde\theta}\psi_s(e^{-j\tilde\theta}i) \approx \psi_s(i) +
j\tilde\theta\psi_a$ ($\tilde\theta = \theta - \hat\theta$): that is what defines
$\psi_a$. With $\tilde\psi = \psi - \hat\psi$, $e = \tilde\psi - j\tilde\theta\psi_a$ and
$\varepsilon = \tilde\theta - \mathrm{Im}\{\tilde\psi/\psi_a\}$: once the flux error has
decayed, $\varepsilon$ is the angle error itself. Both fluxes turn with the frame, so
$\dot{\tilde\psi} = -j\omega_c\tilde\psi - 2k_1\psi_a\mathrm{Re}\{e/\psi_a\}$, and
$\mathrm{Re}\{e/\psi_a\} = \mathrm{Re}\{\tilde\psi/\psi_a\}$ to first order. With
$z = \tilde\psi/\psi_a$ the linearisation is block triangular:
$\dot z = -j\omega z - 2k_1\mathrm{Re}\,z$ (characteristic polynomial $s^2 + 2k_1 s +
\omega^2$) drives $\dot{\tilde\theta} = \tilde\omega - k_\theta\varepsilon$,
$\dot{\tilde\omega} = -k_\omega\varepsilon$ ($s^2 + k_\theta s + k_\omega = (s +
\alpha_o)^2$). The error dynamics' characteristic polynomial is therefore
$(s^2 + 2k_1 s + \omega^2)(s + \alpha_o)^2$ (`test_reduced_order.py`): the speed
adaptation has its double pole at $-\alpha_o$ at every speed and load, and the flux
poles have the damping $\zeta_\infty + \sigma_0/|\omega|$.

*PM-flux adaptation* (`k_f` > 0): with a true PM flux $\hat\psi_f + \Delta$ the steady
state of the equations above (at $\omega \ne 0$) has $\varepsilon = 0$ and
$\mathrm{Re}\{e/\psi_a\} = -\Delta\,\mathrm{Re}\{1/\psi_a\} = -\Delta\psi_{ad}/|\psi_a|^2$,
while its angle error is $\tilde\theta = \Delta(\psi_{aq} - 2k_1\psi_{ad}/\omega)/
|\psi_a|^2$. The law

$$\frac{d\hat\psi_f}{dt} = -k_f|\psi_a|\,\mathrm{Re}\{e/\psi_a\}$$

therefore moves $\hat\psi_f$ towards the true flux: quasi-statically $\dot\Delta =
-k_f(\psi_{ad}/|\psi_a|)\Delta$, a time constant $1/k_f$ at no load. (The factor
$|\psi_a|$ makes $k_f$ a rate in 1/s; the signal $-\mathrm{Re}\{e/\psi_a\}$ is
dimensionless.) At standstill the signal carries no information and a resistance error
biases it at low speed (the PM flux and $R_s$ are not separable there), so adapt at
speed only and keep $k_f$ well below $\alpha_o$ and $k_1$.

**Defaults** (`from_drive`): $\alpha_o = 2\pi\cdot 40$ rad/s for the speed-estimation
bandwidth (the printed paper was not available here to check its value; 2 pi 40 is just
below the 2 pi 50-100 rad/s usually quoted; for the presets' 5 Hz speed controllers it is
8 times faster; $k_\theta T_s = 0.076$ at `morawiec_ipm3k5`'s 6.6
kHz); $\sigma_0 = \tfrac14 R_s(1/L_d + 1/L_q)$ and $\zeta_\infty = 0.2$, the authors'
flux gain; $k_f = 0$ (no PM-flux adaptation).

**Discretisation** (the `step`). With $\hat\psi_{ab} = e^{j\hat\theta}\hat\psi$ (stored
in stationary coordinates) the frame-rotation term $-j\omega_c\hat\psi$ cancels exactly:
$d\hat\psi_{ab}/dt = u_{ab} - R_s i_{ab} + e^{j\hat\theta}(k_1e + k_2e^*)$. At $t_k$ the
observer receives $i_{ab,k}$ and the voltage $u_{ab}$ realised over $[t_{k-1}, t_k)$,
and integrates over that interval:

- voltage: exact for the zero-order hold, $T_s u_{ab}$;
- resistive drop: trapezoid, $\tfrac12 T_s R_s(i_{ab,k-1} + i_{ab,k})$ ($i_{ab,k-1}$ is
  in the state). With plain forward Euler on this term and on the rotation, a matched
  observer at zero error would leave it by $O(T_s^2)$ every step;
- everything else by forward Euler from $t_{k-1}$: $e$, $\psi_a$, $\varepsilon$, $k_1$
  from the state and $i_{k-1}$ in the frame $\hat\theta_{k-1}$; $\hat\theta_k =
  \hat\theta_{k-1} + T_s\omega_c$, $\hat\omega_k = \hat\omega_{k-1} + T_sk_\omega
  \varepsilon$, $\hat\psi_{f,k} = \hat\psi_{f,k-1} - T_sk_f|\psi_a|\mathrm{Re}
  \{e/\psi_a\}$. The flux correction is held constant in the estimated frame, which
  turns at $\omega_c$ over the interval; its exact integral is $T_s\,\mathrm{sinc}
  (\omega_cT_s/2)\,e^{j(\hat\theta_{k-1} + \omega_cT_s/2)}(k_1e + k_2e^*)$ (rotating
  it with $\hat\theta_{k-1}$ would lag by $\omega_cT_s/2$). With this rule and a
  matched $R_s$ the fixed points of one step are the equilibria of the continuous
  error dynamics exactly, and the Jacobian of a step is $I + T_sA + O(T_s^2)$.

The estimate at $t_k$ is the state after this update ($\hat\omega$ is the integral
state, not $\omega_c$). At $k = 0$ nothing is integrated: $\hat\psi_{ab} =
e^{j\hat\theta_0}\psi_s(i_0)$ ($e_0 = 0$: the observer trusts its initial angle).

**Error coordinates** (`error_rhs`; true minus estimate): the flux error $\tilde\psi =
\psi - \hat\psi$ in the estimated frame (fundamental PM flux), $\tilde\theta$,
$\tilde\omega = \omega - \hat\omega$. The PM-flux estimate is not among them: the
analysis holds it at the model's `motor.psi_f` (the observer with $k_f = 0$, or its
dynamics on the time scale of $\alpha_o$ and $k_1$ with a slow adaptation frozen);
`observer_state` sets the adapted correction to zero and `error_state` ignores it.

**Saturated machines** (`with_magnetic`, docs/observers.md): the scheduled model
evaluates the map's apparent $L_d$, $L_q$, $\psi_f$ at $i_{k-1}$ in the estimated frame,
the current at which $e$ is formed, so that $\psi_s(i)$ is the map's flux
$\psi_{dq}(i_{k-1})$ (plus any adapted PM-flux correction), and $\psi_a$ and $k_1$ follow
the apparent values.
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._frames import park, rotate, wrap_angle
from .._plant._params import Drive, PMSMParams
from .._validate import check_positive, is_concrete
from ._base import (
    AbstractObserver,
    ErrorCoordinates,
    Estimate,
    Measurement,
    OperatingPoint,
    PlantPoint,
)
from ._flux_coordinates import (
    flux_error_scale,
    flux_errors,
    flux_estimates,
    model_flux_dq,
    previous_current_dq,
)


#: The authors' published default speed-estimation bandwidth of this observer (rad/s).
ALPHA_O = 2 * math.pi * 40.0
#: The flux gain's damping at high speed (-): k_1 = sigma0 + ZETA_INF |w_hat|.
ZETA_INF = 0.2


def default_sigma0(motor: PMSMParams):
    """The flux gain at standstill, $\\sigma_0 = \\tfrac14 R_s(1/L_d + 1/L_q)$ (1/s)."""
    return 0.25 * motor.R_s * (1.0 / motor.L_d + 1.0 / motor.L_q)


_DESIGN_UNITS = {
    "alpha_o": "rad/s, speed-adaptation bandwidth: k_theta = 2 alpha_o, k_w = alpha_o^2 "
               "(double pole at -alpha_o)",
    "sigma0": "1/s, flux gain at standstill, k_1 = sigma0 + zeta_inf |w_hat|",
    "zeta_inf": "-, flux-observer damping at high speed",
    "k_f": "1/s, PM-flux adaptation rate (0: off)",
}

_COORDS = ErrorCoordinates(
    names=("psi_d", "psi_q", "theta", "w"), units=("V s", "V s", "rad", "rad/s"), angle=2,
    doc=("stator-flux error psi - psi_hat, estimated frame d axis",
         "stator-flux error psi - psi_hat, estimated frame q axis",
         "angle error theta - theta_hat",
         "speed error w - w_hat (w_hat: the speed-adaptation state)"))


class ReducedOrderState(eqx.Module):
    """State of `ReducedOrderObserver`.

    - `psi_ab`: estimated stator flux, stationary frame (V s, (2,)).
    - `theta`: estimated electrical angle, wrapped to (-pi, pi] (rad).
    - `w`: estimated electrical speed $\\hat\\omega$, the speed-adaptation state (rad/s).
    - `dpsi_f`: adapted correction to the model's PM flux (V s); 0 without adaptation.
    - `i_prev`: current sampled at the previous instant (A, stationary frame).
    - `started`: False until the first sample has been seen.
    """

    psi_ab: jnp.ndarray
    theta: jnp.ndarray
    w: jnp.ndarray
    dpsi_f: jnp.ndarray
    i_prev: jnp.ndarray
    started: jnp.ndarray


def _aux_flux(motor: PMSMParams, i_dq, psi_f):
    """$\\psi_a = \\psi_f + (L_d - L_q)(i_d - ji_q)$ (V s, estimated frame)."""
    dL = motor.L_d - motor.L_q
    return jnp.stack([psi_f + dL * i_dq[..., 0], -dL * i_dq[..., 1]], -1)


def _signals(e, psi_a):
    """`(Re{e/psi_a}, Im{e/psi_a})`, both dimensionless."""
    n = psi_a[..., 0] ** 2 + psi_a[..., 1] ** 2
    re = (e[..., 0] * psi_a[..., 0] + e[..., 1] * psi_a[..., 1]) / n
    im = (psi_a[..., 0] * e[..., 1] - psi_a[..., 1] * e[..., 0]) / n
    return re, im


def _true_flux(plant: PMSMParams, i_dq, theta_err):
    """The true machine's stator flux in the estimated frame (V s): the current `i_dq`
    (A, estimated frame) is $e^{-j\\tilde\\theta}i$ in rotor coordinates."""
    i_r = rotate(i_dq, -theta_err)
    return rotate(model_flux_dq(plant, i_r, plant.psi_f), theta_err)


class ReducedOrderObserver(AbstractObserver):
    r"""Reduced-order flux observer with speed adaptation (Hinkkanen et al. 2018) and
    optional PM-flux adaptation (Tuovinen et al. 2018), in estimated rotor coordinates.

    See the module docstring for the equations, the derivation of their signs and of
    the linearised poles $(s^2 + 2k_1s + \omega^2)(s + \alpha_o)^2$, and the
    discretisation. Returns $\hat\theta$ and $\hat\omega$ (the speed-adaptation state);
    extras `psi_ab_hat` (V s) and `psi_f_hat` (V s).

    **Arguments:**

    - `motor`: the observer's machine model (`PMSMParams`); its `psi_f` is the initial
      PM-flux estimate.
    - `alpha_o`: speed-adaptation bandwidth (rad/s), > 0: $k_\theta = 2\alpha_o$,
      $k_\omega = \alpha_o^2$.
    - `sigma0`: flux gain at standstill (1/s), >= 0.
    - `zeta_inf`: flux damping at high speed (-), >= 0.
    - `k_f`: PM-flux adaptation rate (1/s), >= 0 (0: off).
    """

    motor: PMSMParams
    alpha_o: float
    sigma0: float
    zeta_inf: float
    k_f: float

    coordinates: ClassVar[ErrorCoordinates] = _COORDS
    design_units: ClassVar[dict[str, str]] = _DESIGN_UNITS
    extras: ClassVar[dict[str, str]] = {
        "psi_ab_hat": "V s, estimated stator flux, stationary frame (2,)",
        "psi_f_hat": "V s, the PM flux the observer's model uses (adapted with k_f > 0)"}
    # factors 1/4..4: alpha_o T_s <= 0.15 at 6.6 kHz; zeta_inf 0.05..0.8
    tunable: ClassVar[dict[str, tuple[float, float]]] = {
        "alpha_o": (0.25, 4.0), "zeta_inf": (0.25, 4.0)}
    tunable_kinds: ClassVar[dict[str, str]] = {"alpha_o": "tracking"}
    paper_motor: ClassVar[str] = "morawiec_ipm3k5"
    paper_T_s: ClassVar[float] = 1 / 6600
    c_emitter: ClassVar[str] = "_reduced_order:emit"

    def __check_init__(self):
        if not isinstance(self.motor, PMSMParams):
            raise ValueError(f"`ReducedOrderObserver(motor=...)` must be a `PMSMParams` "
                             f"(the observer's machine model); got "
                             f"{type(self.motor).__name__}.")
        _check_design("ReducedOrderObserver", self.design_parameters())

    # --- design -----------------------------------------------------------------------
    @classmethod
    def from_drive(cls, drive: Drive, *, motor: PMSMParams | None = None, **design):
        """The authors' design for `drive`: `alpha_o` = 2 pi 40 rad/s, `sigma0` =
        R_s (1/L_d + 1/L_q) / 4 of the observer's model, `zeta_inf` = 0.2, `k_f` = 0.
        `motor` replaces the observer's machine model (default the drive's); `design`
        overrides design parameters by name (`design_units`)."""
        if not isinstance(drive, Drive):
            raise ValueError(f"`ReducedOrderObserver.from_drive(drive=...)` must be a "
                             f"`Drive`; got {type(drive).__name__}.")
        motor = drive.three_phase_motor if motor is None else motor
        if not isinstance(motor, PMSMParams):
            raise ValueError(f"`ReducedOrderObserver.from_drive(motor=...)` must be a "
                             f"`PMSMParams`; got {type(motor).__name__}.")
        obs = cls(motor=motor, alpha_o=ALPHA_O, sigma0=default_sigma0(motor),
                  zeta_inf=ZETA_INF, k_f=0.0)
        return obs.with_design(**design) if design else obs

    def with_design(self, **values):
        self._check_design_names(values)
        if not values:
            return self
        _check_design("ReducedOrderObserver.with_design", values)
        return self._replace(**values)

    def gains(self, w_hat):
        """`(k_1, k_theta, k_w)` at the speed estimate `w_hat` (rad/s): 1/s, 1/s,
        1/s^2."""
        return (self.sigma0 + self.zeta_inf * jnp.abs(w_hat), 2.0 * self.alpha_o,
                self.alpha_o ** 2)

    def check_values(self, T_s) -> None:
        super().check_values(T_s)
        if not is_concrete((T_s, self.alpha_o, self.sigma0)):
            return
        # forward Euler: the angle loop's gain k_theta and the flux gain at standstill
        # 2 sigma0 must stay well inside the step's stability limit
        for name, rate in (("alpha_o", 2.0 * float(self.alpha_o)),
                           ("sigma0", 2.0 * float(self.sigma0))):
            if not rate * float(T_s) < 1.0:
                raise ValueError(
                    f"`ReducedOrderObserver({name}=...)`: 2 {name} T_s must be below 1 "
                    f"(forward Euler); got 2 x {float(rate) / 2!r} x {float(T_s)!r} s.")

    # --- the observer's right-hand side -----------------------------------------------
    def _feedback(self, psi, w_hat, i_dq, dpsi_f):
        """From the flux estimate `psi` (V s), speed state `w_hat` (rad/s), current
        `i_dq` (A) (both in the estimated frame) and the PM-flux correction: `(frame speed
        w_c (rad/s), flux correction k_1 e + k_2 e* (V/s, estimated frame), dw_hat/dt
        (rad/s^2), dpsi_f/dt (V))`."""
        m = self.motor
        psi_f = m.psi_f + dpsi_f
        e = model_flux_dq(m, i_dq, psi_f) - psi
        psi_a = _aux_flux(m, i_dq, psi_f)
        re, im = _signals(e, psi_a)
        eps = -im
        k_1, k_theta, k_w = self.gains(w_hat)
        w_c = w_hat + k_theta * eps
        corr = (2.0 * k_1 * re)[..., None] * psi_a
        dpsi_f_dt = -self.k_f * jnp.sqrt(psi_a[..., 0] ** 2 + psi_a[..., 1] ** 2) * re
        return w_c, corr, k_w * eps, dpsi_f_dt

    # --- running ----------------------------------------------------------------------
    def init(self, theta0=0.0, w0=0.0) -> ReducedOrderState:
        theta0 = jnp.asarray(theta0)
        w0 = jnp.asarray(w0)
        dtype = jnp.result_type(theta0, w0, float)
        zero2 = jnp.zeros(2, dtype)
        return ReducedOrderState(psi_ab=zero2, theta=wrap_angle(theta0.astype(dtype)),
                                 w=w0.astype(dtype), dpsi_f=jnp.zeros((), dtype),
                                 i_prev=zero2, started=jnp.asarray(False))

    # the step forms its correction at i_{k-1}: the scheduled model is the map's there
    _schedule_current = staticmethod(previous_current_dq)

    def step(self, state: ReducedOrderState, meas: Measurement, T_s):
        self = self._scheduled(state, meas)  # noqa: PLW0642 (the current-scheduled model)
        m = self.motor
        th = state.theta
        i_k = jnp.asarray(meas.i_ab).astype(state.i_prev.dtype)
        w_c, corr, dw, dpf = self._feedback(park(state.psi_ab, th), state.w,
                                            park(state.i_prev, th), state.dpsi_f)
        half = 0.5 * T_s * w_c
        psi = (state.psi_ab + T_s * meas.u_ab - (0.5 * T_s * m.R_s) * (state.i_prev + i_k)
               + (T_s * jnp.sinc(half / jnp.pi)) * rotate(corr, th + half))
        go = state.started
        psi0 = rotate(model_flux_dq(m, park(i_k, th), m.psi_f + state.dpsi_f), th)
        psi = jnp.where(go, psi, psi0).astype(state.psi_ab.dtype)
        theta = jnp.where(go, wrap_angle(th + T_s * w_c), th).astype(th.dtype)
        w = jnp.where(go, state.w + T_s * dw, state.w).astype(state.w.dtype)
        dpsi_f = jnp.where(go, state.dpsi_f + T_s * dpf,
                           state.dpsi_f).astype(state.dpsi_f.dtype)
        new = ReducedOrderState(psi_ab=psi, theta=theta, w=w, dpsi_f=dpsi_f, i_prev=i_k,
                                started=jnp.ones_like(state.started))
        return new, Estimate(theta_hat=theta, w_hat=w,
                             extras={"psi_ab_hat": psi,
                                     "psi_f_hat": (m.psi_f + dpsi_f).astype(psi.dtype)})

    # --- analysis ---------------------------------------------------------------------
    def error_rhs(self, x, op: OperatingPoint, plant: PMSMParams):
        """The continuous error dynamics (module docstring) against the true machine
        `plant` (fundamental PM flux) with ideal current control holding `op.i_dq` in
        the estimated frame at constant speed `op.w_m`; the PM-flux estimate held at the
        model's (no adaptation state). Exact (nonlinear), the gain k_1 at the observer's
        own speed estimate, as the step schedules it."""
        x = jnp.asarray(x)
        dtype = x.dtype
        w = jnp.asarray(op.w_m, dtype)
        i = jnp.asarray(op.i_dq, dtype)
        th_err, w_hat = x[2], w - x[3]
        psi_hat = _true_flux(plant, i, th_err) - x[:2]
        w_c, corr, dw, _ = self._feedback(psi_hat, w_hat, i, jnp.zeros((), dtype))
        # both fluxes turn with the frame (-j w_c psi); the voltage cancels, the
        # resistances differ by the model error
        dpsi = (-(plant.R_s - self.motor.R_s) * i + w_c * jnp.stack([x[1], -x[0]])
                - corr)
        return jnp.concatenate([dpsi, jnp.stack([w - w_c, -dw])])

    def error_scale(self, op: OperatingPoint, plant: PMSMParams):
        del plant
        pa = _aux_flux(self.motor, jnp.asarray(op.i_dq), self.motor.psi_f)
        return flux_error_scale(jnp.sqrt(jnp.sum(pa ** 2)), op.w_m)

    def error_state(self, state: ReducedOrderState, truth: PlantPoint, plant: PMSMParams):
        return flux_errors(state.psi_ab, state.theta, state.w, truth, plant)

    def observer_state(self, x, truth: PlantPoint, plant: PMSMParams) -> ReducedOrderState:
        psi, theta, w = flux_estimates(x, truth, plant)
        return ReducedOrderState(psi_ab=psi, theta=theta, w=w, dpsi_f=jnp.zeros((), psi.dtype),
                                 i_prev=jnp.asarray(truth.i_ab, psi.dtype),
                                 started=jnp.asarray(True))


def _check_design(owner: str, values: dict) -> None:
    """`ValueError` naming the design parameter out of range (concrete values only)."""
    for k, v in values.items():
        check_positive(owner, k, v, _DESIGN_UNITS[k].split(",")[0],
                       allow_zero=k != "alpha_o")
