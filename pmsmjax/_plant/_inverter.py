r"""Inverter non-linearity: the dead-time and device-drop voltage error of a two-level
voltage-source inverter, per phase, as a function of the phase current: the hard model
$u_{dt}\,\mathrm{sign}(i_x)$ or the smooth one $u_{dt}\tanh(i_x / i_{dt})$.

**Model.** During the dead time $t_d$ of each switching period $T_{sw}$ neither switch of a
leg conducts and the freewheeling diode sets the phase's potential by the sign of the
phase current; the switches and diodes add an on-state drop with the same sign. Averaged
over a switching period, the phase voltage falls short of the commanded one by

$$\Delta u_x = u_{dt}\,\tanh(i_x / i_{dt}), \qquad x \in \{a, b, c\},
\qquad u_{dt} \approx \frac{t_d}{T_{sw}} u_{dc} + u_{on},$$

so the voltage the machine receives is $u_x = u_x^* - \Delta u_x$. Far from zero current
this is the classical square-wave error $u_{dt}\,\mathrm{sign}(i_x)$. Near zero current the
switches' output capacitances are charged by the phase current itself during the dead
time, so the error grows with the current instead of jumping: $\tanh(i_x / i_{dt})$ is
that smooth transition, linear for $|i_x| \ll i_{dt}$ (slope $u_{dt}/i_{dt}$, an apparent
resistance) and within 2 % of $u_{dt}$ beyond $|i_x| = 2.3\,i_{dt}$. The transition
width $i_{dt}$ is of the order of $2 C_{oss} u_{dc} / t_d$, a few percent of rated current.

**Hard and smooth: `i_dt = 0` is the hard model.** $i_{dt} = 0$ selects
$\Delta u_x = u_{dt}\,\mathrm{sign}(i_x)$ (0 at $i_x = 0$), the limit of the smooth
model as $i_{dt} \to 0$, so one parameter spans both and every place that takes an
`Inverter` (plant, `observer_voltage`, replay, identification, motor files, `--set
i_dt=0`, the generated C) takes the hard model with it. A Python zero is a static
decision (the hard form is compiled, at no cost, as an ideal inverter's `u_dt = None` is);
a traced zero selects it per element. Differentiability: both models are linear in
$u_{dt}$, so gradients with respect to $u_{dt}$ (its identification, tuning) are exact for
either. The hard model's derivative with respect to the current is zero (undefined at
the jump), so a gradient through a simulated trajectory misses how a parameter moves the
zero crossings; the smooth model keeps the plant differentiable in the current and in
$i_{dt}$ (`pmsmjax identify --fit i_dt` fits it, in log space: it starts from a positive
value, i.e. from the smooth model).

The error vector is the amplitude-invariant Clarke transform of the three phase errors,
whose zero-sequence part does not reach the star-connected windings. For sinusoidal
currents of amplitude $|i| \gg i_{dt}$ its fundamental is

$$\Delta u_{dq} \approx \frac{4}{\pi}\,u_{dt}\,\frac{i_{dq}}{|i_{dq}|},$$

in phase with the current (an equivalent resistance $4u_{dt}/(\pi|i|)$; exact for the hard
model), with a sixth harmonic ripple in rotor coordinates (`dead_time_fundamental` gives
the exact fundamental of either model). A dual three-phase machine has two such
inverters, one per winding set; their six phase errors map through the vector-space
decomposition to alpha-beta and x-y voltages.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from .._frames import inv_vsd, vsd
from .._validate import is_concrete


_S3 = math.sqrt(3.0)


def is_hard(i_dt) -> bool:
    """`i_dt` is a Python zero: the hard model, a static decision (module docstring)."""
    return isinstance(i_dt, (int, float)) and not isinstance(i_dt, bool) and i_dt == 0


def _phase_error(u_dt, i_dt, i_x):
    """`u_dt tanh(i_x / i_dt)`, or `u_dt sign(i_x)` where `i_dt` is 0 (V)."""
    if is_hard(i_dt):
        return u_dt * jnp.sign(i_x)
    if is_concrete(i_dt) and np.all(np.asarray(i_dt) > 0):
        return u_dt * jnp.tanh(i_x / i_dt)
    smooth = i_dt > 0  # traced (or mixed) widths: the hard model where one is zero
    return u_dt * jnp.where(smooth, jnp.tanh(i_x / jnp.where(smooth, i_dt, 1.0)),
                            jnp.sign(i_x))


def dead_time_error_ab(u_dt, i_dt, i_a, i_b):
    r"""Voltage error $\Delta u_{\alpha\beta}$ (V) of a three-phase inverter at the current
    with stationary components `(i_a, i_b)` (A): commanded minus applied voltage.

    Works on components (any equal shapes) and returns the components `(du_a, du_b)`.

    **Arguments:**

    - `u_dt`: the error's amplitude per phase (V), >= 0.
    - `i_dt`: width of its transition around zero current (A), >= 0; 0 is the hard
      model `u_dt sign(i_x)` (module docstring).
    - `i_a`, `i_b`: stationary-frame current components (A).
    """
    # phase currents (inverse amplitude-invariant Clarke)
    ia = i_a
    ib = -0.5 * i_a + 0.5 * _S3 * i_b
    ic = -0.5 * i_a - 0.5 * _S3 * i_b
    ea, eb, ec = (_phase_error(u_dt, i_dt, x) for x in (ia, ib, ic))
    return (2.0 / 3.0) * (ea - 0.5 * (eb + ec)), (eb - ec) / _S3


def dead_time_error_vsd(u_dt, i_dt, i_ab, i_xy):
    """Voltage errors `(du_ab, du_xy)` (V, last axis 2) of the two inverters of a dual
    three-phase machine at the alpha-beta and x-y currents `i_ab`, `i_xy` (A, last axis 2)
    (see `pmsmjax.vsd_matrix`)."""
    i6 = inv_vsd(i_ab, i_xy)
    du_ab, du_xy, _ = vsd(_phase_error(u_dt, i_dt, i6))
    return du_ab, du_xy


def observer_voltage(u_cmd_prev, i_prev, i_now, u_dt, i_dt):
    """The voltage a drive's observer sees for the period that ended at the present sample:
    the commanded voltage `u_cmd_prev` (V, last axis 2) less the inverter error model
    (`u_dt` V, `i_dt` A; `i_dt = 0`: the hard model) averaged over the measured currents
    at the period's two ends `i_prev`, `i_now` (A, last axis 2) (trapezoid rule)."""
    e0 = dead_time_error_ab(u_dt, i_dt, i_prev[..., 0], i_prev[..., 1])
    e1 = dead_time_error_ab(u_dt, i_dt, i_now[..., 0], i_now[..., 1])
    return u_cmd_prev - 0.5 * (jnp.stack(e0, -1) + jnp.stack(e1, -1))


def dead_time_fundamental(u_dt, i_dt, i_amp, n: int = 720):
    r"""Fundamental of the dead-time error along the current (V) for a sinusoidal current of
    amplitude `i_amp` (A): $\frac{1}{\pi}\int_0^{2\pi} u_{dt}\tanh(\hat i\cos\phi/i_{dt})
    \cos\phi\,d\phi$ (its limit for $\hat i \gg i_{dt}$ is $4u_{dt}/\pi$; `i_dt = 0`,
    the hard model: $4u_{dt}/\pi$ for every $\hat i > 0$). NumPy, for analysis; `n`
    quadrature points (the smooth integrand is periodic: the rectangle rule converges
    geometrically)."""
    i_amp = np.asarray(i_amp, dtype=float)
    if float(i_dt) == 0.0:
        return np.where(i_amp > 0, 4.0 * float(u_dt) / np.pi, 0.0)
    phi = (np.arange(n) + 0.5) * (2.0 * np.pi / n)
    i_amp = i_amp[..., None]
    f = u_dt * np.tanh(i_amp * np.cos(phi) / i_dt) * np.cos(phi)
    return f.mean(-1) * 2.0
