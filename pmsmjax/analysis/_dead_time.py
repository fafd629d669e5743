r"""Static angle error caused by the inverter's dead-time error (any observer).

An observer that is handed the *commanded* voltage, while the windings receive it less
the inverter error $\Delta u$ (`pmsmjax._plant._inverter`), sees a machine whose voltage
equation carries $\Delta u$ on top of its own. In steady state the error's fundamental in
rotor coordinates lies along the current,

$$\Delta u_{dq} = \frac{F(|i|)}{|i|}\, i_{dq},\qquad
F(\hat\imath) = \frac1\pi\int_0^{2\pi} u_{dt}\tanh\!\Big(\frac{\hat\imath\cos\phi}{i_{dt}}
\Big)\cos\phi\,d\phi \;\xrightarrow{\hat\imath \gg i_{dt}}\; \frac4\pi u_{dt},$$

which is exactly an extra stator resistance $R_{dt} = F(|i|)/|i|$ in the true machine
that the observer's model lacks. So the static angle error is the principal equilibrium
of the observer's error dynamics (`pmsmjax.analysis.equilibria`) for a plant with
resistance $R_s + R_{dt}$: the same route as any resistance mismatch. The sixth harmonic
of $\Delta u_{dq}$ makes a ripple about that mean which this analysis leaves out (its
amplitude is what `harmonic_ripple` measures for a voltage harmonic). When the
compensation model differs from the truth, $u_{dt}$ here is the uncompensated part,
the true error less the model's. At zero current $F(0)/0$ is the small-signal slope
$u_{dt}/i_{dt}$, but the equivalence then describes no steady state worth the name
(no torque, no current to carry the error).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._plant._inverter import dead_time_fundamental
from ..observers import AbstractObserver
from ._generic import equilibria


def dead_time_resistance(u_dt, i_dt, i_amp):
    """Equivalent series resistance (Ohm) of the dead-time error's fundamental at a
    sinusoidal current of amplitude `i_amp` (A): `F(i_amp) / i_amp` (module docstring);
    `u_dt / i_dt` at zero current (the small-signal slope; infinite for the hard model,
    `i_dt = 0`). NumPy."""
    i_amp = np.asarray(i_amp, dtype=float)
    safe = np.where(i_amp > 0, i_amp, 1.0)
    slope = float(u_dt) / float(i_dt) if float(i_dt) > 0 else math.inf
    return np.where(i_amp > 0, dead_time_fundamental(u_dt, i_dt, safe) / safe, slope)


def dead_time_angle_error(observer: AbstractObserver, plant, w_m, i_dq, u_dt, i_dt=0.1,
                          **options):
    """Static angle error (rad, true minus estimate) of `observer` at electrical speed `w_m`
    (rad/s) and current `i_dq` (A, `(2,)`) when it is handed voltages that carry an
    uncompensated inverter error `u_dt` (V per phase, transition width `i_dt` A) (module
    docstring). `plant` is the true machine (`PMSMParams`); `options` go to
    `equilibria`. Returns the principal equilibrium's angle, NaN where the error dynamics
    have no equilibrium (the estimate drifts: loss of lock)."""
    i_amp = math.hypot(float(i_dq[0]), float(i_dq[1]))
    R_dt = float(dead_time_resistance(u_dt, i_dt, i_amp))
    plant_eff = eqx.tree_at(lambda p: p.R_s, plant, plant.R_s + R_dt)
    eq = equilibria(observer, plant_eff, w_m, jnp.asarray(i_dq, dtype=float), **options)
    theta = jnp.take_along_axis(eq.theta, eq.principal[..., None], -1)[..., 0]
    return jnp.where(eq.n > 0, theta, jnp.nan)
