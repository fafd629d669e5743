"""Harmonic sensitivity (`analysis.harmonic_ripple`): the angle-error ripple a back-EMF
harmonic causes, from the linearisation, against simulations with that harmonic in the
plant (speed imposed, fast current control), for several observer families."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax import analysis
from pmsmjax.observers import make_observer


DRIVE = pj.preset("zhang750")
PLANT = DRIVE.three_phase_motor
W = 0.5 * DRIVE.w_rated
I_DQ = np.array([0.0, 0.3]) * float(DRIVE.base.I_b)
OP = analysis.OperatingPoint(W, jnp.asarray(I_DQ))
ORDERS = (-5, 7, 13)
T_S = 1e-4
N_STEPS = 800


def _simulated_ripple(name):
    """Peak steady-state angle-error ripple (deg) per 1 % harmonic of each order in
    `ORDERS`, from one `simulate` per order (vmapped over a one-hot amplitude): the
    amplitude of theta_err at (h - 1) w over the last two electrical periods (a DFT bin:
    exact for a sinusoid over whole periods, blind to the constant part)."""
    obs = make_observer(name, DRIVE)
    x0 = obs.designed_error(OP, PLANT)
    foc = pj.FOC.from_drive(DRIVE)
    sc = pj.Scenario(t_end=N_STEPS * T_S, w_m_imposed=pj.Profile.constant(W),
                     i_d_ref=pj.Profile.constant(I_DQ[0]),
                     i_q_ref=pj.Profile.constant(I_DQ[1]))

    def one(amp):
        drv = eqx.tree_at(lambda d: d.motor.harmonics, DRIVE,
                          pj.EMFHarmonics(order=ORDERS, amplitude=amp),
                          is_leaf=lambda x: x is None)
        tr = pj.simulate(drv, foc, obs, sc, T_s=T_S, w_m0=W,
                         theta_hat0=-x0[obs.coordinates.angle], w_hat0=W,
                         i_dq0=tuple(I_DQ), throw=False)
        return tr.t, tr.theta_err

    t, err = jax.vmap(one)(0.01 * jnp.eye(len(ORDERS)))
    n_per = int(round(2 * math.pi / W / T_S))
    t, err = np.asarray(t[0, -2 * n_per:]), np.asarray(err[:, -2 * n_per:])
    assert np.all(np.isfinite(err)) and np.max(np.abs(err)) < math.radians(5.0)
    om = (np.asarray(ORDERS)[:, None] - 1) * W
    return np.degrees(np.abs(2 * np.mean(err * np.exp(-1j * om * t[None, :]), 1)))


def test_standstill_vmap_and_float32():
    obs = make_observer("leso", DRIVE)
    ws = jnp.array([0.0, 0.3, -0.5]) * DRIVE.w_rated
    ops = analysis.OperatingPoint(ws, jnp.broadcast_to(jnp.asarray(I_DQ), (3, 2)))
    r = jax.vmap(lambda op: analysis.harmonic_ripple(obs, DRIVE, op, (1, -5, 7)))(ops)
    assert r.shape == (3, 3) and bool(jnp.all(jnp.isfinite(r)))
    np.testing.assert_array_equal(np.asarray(r[0]), 0.0)  # no back-EMF at standstill
    assert bool(jnp.all(r[1:] > 0))
    # each row is the unbatched call
    one = analysis.harmonic_ripple(obs, DRIVE, analysis.OperatingPoint(ws[1], I_DQ), (1, -5, 7))
    np.testing.assert_allclose(np.asarray(r[1]), np.asarray(one), rtol=1e-10)
    # float32 follows the operating point's dtype and agrees
    d32, o32 = pj.astype(DRIVE, jnp.float32), pj.astype(obs, jnp.float32)
    op32 = analysis.OperatingPoint(jnp.float32(ws[1]), jnp.asarray(I_DQ, jnp.float32))
    r32 = analysis.harmonic_ripple(o32, d32, op32, (1, -5, 7))
    assert r32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(r32), np.asarray(r[1]), rtol=2e-3)


def test_bad_arguments():
    obs = make_observer("leso", DRIVE)
    with pytest.raises(ValueError, match="order 0"):
        analysis.harmonic_ripple(obs, DRIVE, OP, (0, 7))
    with pytest.raises(ValueError, match="must be a `Drive`"):
        analysis.harmonic_ripple(obs, PLANT, OP, (7,))
    with pytest.raises(ValueError, match="OperatingPoint"):
        analysis.harmonic_ripple(obs, DRIVE, (W, I_DQ), (7,))
    with pytest.raises(ValueError, match="T_s"):
        analysis.harmonic_ripple(obs, DRIVE, OP, (7,), T_s=0.0)


@pytest.mark.parametrize("name", ["leso"])
def test_ripple_from_the_linearisation_matches_simulation(name):
    obs = make_observer(name, DRIVE)
    sim = _simulated_ripple(name)
    disc = np.asarray(analysis.harmonic_ripple(obs, DRIVE, OP, ORDERS, T_s=T_S))
    cont = np.asarray(analysis.harmonic_ripple(obs, DRIVE, OP, ORDERS))
    np.testing.assert_allclose(disc, sim, rtol=0.02)
    np.testing.assert_allclose(cont, sim, rtol=0.1)
