r"""Current control of a dual three-phase machine (VSD or two individual sets).

The derivation (frames, set vectors, gains) is in `DualCurrentControl`'s docstring.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .._frames import cos_sin
from .._validate import check_positive
from ._controllers import FOCOutput, FOCState
from ._limits import _limited_pi


def _rot(c, s, x, y):
    return c * x - s * y, s * x + c * y


class XYCurrentControllerState(eqx.Module):
    x_I: jnp.ndarray  # PI integrator, anti-synchronous frame (V, (2,))
    x_h: jnp.ndarray  # harmonic integrators at +6 theta and -6 theta (V, (2, 2))


class XYCurrentController(eqx.Module):
    """x-y current control of a dual three-phase machine (see `DualCurrentControl`).

    **Arguments:**

    - `L_xy`: the controller's x-y inductance (H), > 0; `R_s`: resistance (Ohm), > 0.
    - `alpha_xy`: bandwidth of the anti-synchronous PI (rad/s), > 0.
    - `alpha_r`: harmonic-integrator gain relative to `K_p` (rad/s), >= 0 (0: PI only).
    - `u_max`: limit of the x-y voltage vector (V), > 0.
    """

    L_xy: float
    R_s: float
    alpha_xy: float
    alpha_r: float
    u_max: float

    def __check_init__(self):
        check_positive("XYCurrentController", "L_xy", self.L_xy, "H")
        check_positive("XYCurrentController", "R_s", self.R_s, "Ohm")
        check_positive("XYCurrentController", "alpha_xy", self.alpha_xy, "rad/s")
        check_positive("XYCurrentController", "alpha_r", self.alpha_r, "rad/s",
                       allow_zero=True)
        check_positive("XYCurrentController", "u_max", self.u_max, "V")

    def init(self) -> XYCurrentControllerState:
        return XYCurrentControllerState(x_I=jnp.zeros(2), x_h=jnp.zeros((2, 2)))

    def step(self, state, i_ref, i_xy, theta_hat, w_hat, theta_u, T_s):
        """`i_ref` (A, anti-synchronous frame), `i_xy` (A, stationary x-y), `theta_hat`
        (rad) of the sample, `theta_u` (rad) the advanced angle of the output, `w_hat`
        (rad/s). Returns `(state, u_xy)` (V, stationary x-y)."""
        c, s = cos_sin(theta_hat)
        i_x, i_y = _rot(c, s, i_xy[..., 0], i_xy[..., 1])  # anti-synchronous frame
        e_x, e_y = i_ref[..., 0] - i_x, i_ref[..., 1] - i_y
        Kp = self.alpha_xy * self.L_xy
        Ki = self.alpha_xy * self.R_s
        Kr = self.alpha_r * Kp
        c6, s6 = cos_sin(6 * theta_hat)
        ep = _rot(c6, -s6, e_x, e_y)  # error in the +6 theta frame (5th harmonic)
        en = _rot(c6, s6, e_x, e_y)   # error in the -6 theta frame (7th harmonic)
        cu6, su6 = cos_sin(6 * theta_u)
        xp, xn = state.x_h[..., 0, :], state.x_h[..., 1, :]
        hp = _rot(cu6, su6, xp[..., 0], xp[..., 1])
        hn = _rot(cu6, -su6, xn[..., 0], xn[..., 1])
        # PI + decoupling of the frame's rotation (-j w L_xy i) + harmonic terms
        u_x = Kp * e_x + state.x_I[..., 0] + w_hat * self.L_xy * i_y + hp[0] + hn[0]
        u_y = Kp * e_y + state.x_I[..., 1] - w_hat * self.L_xy * i_x + hp[1] + hn[1]
        x_I, (ul_x, ul_y) = _limited_pi((u_x, u_y), (state.x_I[..., 0], state.x_I[..., 1]),
                                        (e_x, e_y), (Kp, Kp), Ki, self.u_max, T_s)
        x_h = jnp.stack([xp + T_s * Kr * jnp.stack(ep, -1),
                         xn + T_s * Kr * jnp.stack(en, -1)], -2)
        cu, su = cos_sin(theta_u)
        u_xy = jnp.stack(_rot(cu, -su, ul_x, ul_y), -1)  # back to stationary x-y
        return XYCurrentControllerState(x_I=x_I, x_h=x_h), u_xy


class DualCurrentControl(eqx.Module):
    r"""Current control of a dual three-phase machine, an option of `FOC` (`FOC.dual`).

    The plant is in vector-space-decomposition (VSD) coordinates (`pmsmjax.PMSM`): the
    alpha-beta subspace makes the torque, the x-y subspace is an R-L circuit
    $L_{xy}\,di_{xy}/dt = u_{xy} - R_s i_{xy} - e_{xy}$ driven by the 5th and 7th PM-flux
    harmonics. With the sets' space vectors $i_1$, $i_2$ (each over its own three phases, in
    the common stationary frame, amplitude invariant) the `vsd_matrix` gives

    $$i_{\alpha\beta} = \tfrac12 (i_1 + i_2), \qquad i_{xy} = \tfrac12\,\overline{(i_1 - i_2)},
    \qquad i_{1,2} = i_{\alpha\beta} \pm \overline{i_{xy}}$$

    (the x-y row of a set-1 phase is the conjugate of its alpha-beta row; for set 2 the
    conjugate times $e^{j6\gamma} = -1$ at $\gamma = 30°$; tested against `vsd_matrix`), and
    the same for the voltages.

    **Which frame for x-y.** A balanced fundamental of different amplitude or phase in the
    two sets, $i_k = i_{dq,k} e^{j\theta}$, gives $i_{xy} = \tfrac12\overline{(i_{dq,1} -
    i_{dq,2})}\,e^{-j\theta}$: constant in the *anti-synchronous* frame, at $-\theta$. The
    back-EMF harmonics of orders $-5$ and $+7$ (alpha-beta convention $e^{jh\theta}$) enter
    x-y conjugated, as $e^{+j5\theta}$ and $e^{-j7\theta}$, i.e. at $e^{\pm j6\theta}$ in the
    anti-synchronous frame: no frame makes both constant, and a PI in the stationary or the
    anti-synchronous frame leaves them (its gain at $\pm 6\omega$ is finite). Hence
    (`XYCurrentController`): a PI with decoupling in the anti-synchronous frame at
    $-\hat\theta$ (constant references, bandwidth $\alpha_{xy}$:
    $K_p = \alpha_{xy} L_{xy}$, $K_i = \alpha_{xy} R_s$) plus two integrators in the harmonic
    frames $\pm 6\hat\theta$ of the anti-synchronous frame (the 5th and 7th synchronous frames
    of the stationary x-y plane), gain $K_r = \alpha_r K_p$ — the same as a resonant term at
    $6\hat\omega$ in the anti-synchronous frame, but tied to the angle, so exact at any
    speed. The output rotations use the advanced angle (as for alpha-beta), which also
    compensates the delay at the 5th and 7th. Each harmonic integrator converges at about
    $\alpha_r\alpha_{xy}/|\alpha_{xy} + j6\omega|$ (phase margin $90° -
    \arctan(6\omega/\alpha_{xy})$): on `li_dtp` at rated speed with the defaults
    ($\alpha_{xy} = 2\pi\,500$, $\alpha_r = \alpha_{xy}/10$) 270 rad/s predicted, about 330
    rad/s simulated (the x-y rms falls 27-fold per 10 ms).

    **Individual sets** (`mode="individual"`, li-fa-leso [6]): each set in its own rotor
    frame (set 2's own Clarke transform at $\hat\theta - \gamma$ is the common-frame vector at
    $\hat\theta$), each with `FOC.current` (its model should be the per-set one: self
    inductance $(L_{d,q} + L_{xy})/2$, see `FOC.from_drive`), both sets the same references;
    the common mode sees $L_{d,q}$ and the differential mode $L_{xy}$, so a gain that gives
    the bandwidth $\alpha_c$ with the self inductance gives $\alpha_c (L_{d,q}+L_{xy})/(2
    L_{xy})$ (3.5 to 5.5 times more on `li_dtp`) to the differential mode. Its discrete
    loop $z - 1 + k$ (or $z(z-1) + k$ with the computational delay), $k = K_p T_s/L_{xy}$,
    needs $k < 2$ ($k < 1$ with the delay): on `li_dtp` at $T_s = 100$ us the default
    $\alpha_c = 2\pi\,500$ gives $k = 1.7$ (stable without the delay, but oscillatory). The
    5th and 7th currents are left in each set, divided by the differential loop (x-y rms
    0.69 A at $\alpha_c = 2\pi\,100$, 0.20 A at $2\pi\,500$, 1.27 A without control, at
    rated speed).

    Simplifications: the x-y voltage has its own limit circle `u_max` and does not reduce
    the alpha-beta limit (VSD mode); the x-y current is sampled without the `Sensing` chain.

    **Arguments:**

    - `mode`: `"vsd"` (alpha-beta by `FOC.current`, x-y by `xy`) or `"individual"` (two
      sets, each by `FOC.current` in its own rotor frame).
    - `xy`: `XYCurrentController` (needed for `"vsd"`).
    - `i_xy_ref`: x-y current reference (A, anti-synchronous frame, (2,)); with VSD
      control; zero by default.
    """

    mode: str = eqx.field(static=True)
    xy: XYCurrentController | None = None
    i_xy_ref: jnp.ndarray | tuple = (0.0, 0.0)

    def __check_init__(self):
        if self.mode not in ("vsd", "individual"):
            raise ValueError(f"`DualCurrentControl(mode=...)` must be 'vsd' or "
                             f"'individual'; got {self.mode!r}.")
        if self.mode == "vsd" and self.xy is None:
            raise ValueError("`DualCurrentControl(mode='vsd')` needs `xy` (an "
                             "`XYCurrentController`); got None.")

    def init(self, foc):
        if self.mode == "vsd":
            return self.xy.init()
        return foc.current.init()  # set 2 (set 1 uses FOCState.current)

    def step(self, foc, state, i_ab, i_xy, theta_hat, theta_u, w_hat, w_ref, T_s, *,
             i_ref_override=None, speed_mode=True):
        """One step. `i_ab`, `i_xy` measured (A, stationary), `theta_hat` (rad) the
        controller angle, `theta_u` (rad) the advanced output angle. Returns `(state,
        FOCOutput, u_xy)`: `FOCOutput.u_dq` is the alpha-beta voltage at `theta_hat`'s
        frame (V), `u_xy` the x-y voltage (V, stationary)."""


        s_state, i_ref, tau_ref = foc._references(state, w_hat, w_ref, T_s,
                                                  i_ref_override, speed_mode)
        c, s = cos_sin(theta_hat)
        if self.mode == "vsd":
            i_dq = jnp.stack(_rot(c, -s, i_ab[..., 0], i_ab[..., 1]), -1)
            c_state, u = foc.current.step(state.current, i_ref, i_dq, w_hat, T_s)
            x_state, u_xy = self.xy.step(state.dual, jnp.asarray(self.i_xy_ref, i_ab.dtype),
                                         i_xy, theta_hat, w_hat, theta_u, T_s)
        else:
            a, b = i_ab[..., 0], i_ab[..., 1]
            x, y = i_xy[..., 0], -i_xy[..., 1]  # conj(i_xy)
            i1 = jnp.stack(_rot(c, -s, a + x, b + y), -1)
            i2 = jnp.stack(_rot(c, -s, a - x, b - y), -1)
            c_state, u1 = foc.current.step(state.current, i_ref, i1, w_hat, T_s)
            x_state, u2 = foc.current.step(state.dual, i_ref, i2, w_hat, T_s)
            u = 0.5 * (u1 + u2)
            d = 0.5 * (u1 - u2)
            cu, su = cos_sin(theta_u)
            dx, dy = _rot(cu, su, d[..., 0], d[..., 1])  # stationary
            u_xy = jnp.stack([dx, -dy], -1)  # conj
        new = FOCState(current=c_state, speed=s_state, dual=x_state)
        return new, FOCOutput(u_dq=u, i_ref=i_ref, tau_ref=tau_ref), u_xy
