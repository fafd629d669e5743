"""Sensorless closed loop with the zhang2022 observers: what the paper's experiments do not
cover.

The paper's experiments themselves (Figs. 2-10: convergence from 30 deg for the ESO, LESO
and AFO, the steady states against the same runs with an encoder, the resistance error
against the equilibrium of (11), the speed and load steps, the noise of Fig. 7, the
Fig. 9 design, the halved inductance) run in notebooks/02_eso_observers.ipynb, which
asserts these checks with the tolerances stated there, next to the paper's numbers. The
simulated drive has no dead time or other inverter non-linearity and white current noise
of 0.02 A (see `pmsmjax.papers.zhang2022`), so its steady-state errors are far below the
paper's measured ones; the bounds are values the model must meet, not the paper's
numbers.
"""

import math

import equinox as eqx
import jax
import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax.papers import zhang2022


DRIVE = pj.preset("zhang750")
M = DRIVE.motor
WR = float(DRIVE.w_rated)


def stable_deg(eq):
    """Angles (deg) of the stable equilibria of an `Equilibria`."""
    return np.degrees(np.asarray(eq.theta)[np.asarray(eq.stable)])


def test_delay_noise_initial_error_and_mismatch_step():
    """Computational delay, noise, a 30 deg initial error, and a step in the observer's
    R_s (x1.5) and inductances (x0.8) mid-run: before the step the error is below
    0.2 deg; after it, the static error equals the stable equilibrium of the error
    dynamics (11) with that mismatch, within 0.3 deg."""
    drive = eqx.tree_at(lambda d: d.inverter, DRIVE, pj.Inverter(u_dc=311.0, delay=True))
    obs = pj.ESOObserver.from_drive(drive)
    step = lambda v: pj.Profile.steps([0.6], [v], 1.0)  # noqa: E731
    sc = pj.Scenario(t_end=1.2, w_m_ref=pj.Profile.constant(0.5 * WR),
                     tau_L=pj.Profile.constant(0.5 * float(DRIVE.tau_rated)),
                     observer_scale={"R_s": step(1.5), "L_d": step(0.8), "L_q": step(0.8)})
    tr = pj.simulate(drive, pj.FOC.from_drive(drive), obs, sc, w_m0=0.5 * WR,
                     theta_hat0=-math.radians(30), sensing=pj.Sensing(noise_std=0.02),
                     key=jax.random.PRNGKey(1))
    t, e = np.asarray(tr.t), np.degrees(np.asarray(tr.theta_err))
    before = e[(t >= 0.3) & (t < 0.6)]
    after = e[t >= 0.9]
    assert abs(before.mean()) < 0.2 and before.std() < 0.2
    i_c = np.asarray(pj.park(tr.i_meas_ab, tr.theta_hat))[t >= 0.9].mean(0)
    obs_hat = obs.with_motor(pj.scale_motor(M, {"R_s": 1.5, "L_d": 0.8, "L_q": 0.8}))
    eq = stable_deg(pj.analysis.equilibria(obs_hat, M, 0.5 * WR, i_c))
    assert len(eq) == 1
    assert abs(after.mean()) > 3.0
    assert after.mean() == pytest.approx(eq[0], abs=0.3)


def test_adaptive_and_fixed_gains_fig11():
    """Fig. 11 from zero initial conditions: at 0.2 p.u. both designs converge within
    0.1 s; at 0.6 p.u. both converge with a 250 Hz bandwidth (with the paper's 50 Hz
    default neither pulls in from w_hat = 0: the 754 rad/s offset is beyond the
    speed loop's pull-in range; see the notebook)."""
    for w_pu, bw in ((0.2, 50.0), (0.6, 250.0)):
        r = zhang2022.experiment("fig11", w_pu=w_pu, bandwidth_hz=bw).run()
        for name in ("adaptive", "fixed"):
            s = r.stats[name]
            assert s["t_w_converge_s"] < 0.1, (w_pu, name, s)
            assert abs(s["theta_err_mean_deg"]) < 0.2
