"""Harmonic sensitivity (`analysis.harmonic_ripple`): the angle-error ripple a back-EMF
harmonic causes, from the linearisation, against simulations with that harmonic in the
plant (speed imposed, fast current control), for several observer families."""

import copy
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


def _with_harmonics(drive, amp, phase=0.0):
    return eqx.tree_at(lambda d: d.motor.harmonics, drive,
                       pj.EMFHarmonics(order=ORDERS, amplitude=amp,
                                       phase=phase * jnp.ones(len(ORDERS))),
                       is_leaf=lambda x: x is None)


def _ripple(t, err, w):
    """Peak (half peak-to-peak) and the amplitude at (h - 1) w (a DFT bin, exact for a
    sinusoid over whole periods) of the angle error each harmonic adds, over the last
    two electrical periods, in deg. Row 0 of `err` is the run without harmonics: it is
    subtracted, so that what is left of the start-up transient cancels; the other rows
    cycle through `ORDERS`."""
    n_per = int(round(2 * math.pi / abs(w) / T_S))
    t = np.asarray(t)[-2 * n_per:]
    err = np.asarray(err)[:, -2 * n_per:]
    assert np.all(np.isfinite(err)) and np.max(np.abs(err)) < math.radians(5.0)
    diff = err[1:] - err[:1]
    om = np.resize((np.asarray(ORDERS) - 1) * w, diff.shape[0])[:, None]
    peak = np.degrees(np.ptp(diff, 1) / 2)
    dft = np.degrees(np.abs(2 * np.mean(diff * np.exp(-1j * om * t[None, :]), 1)))
    return peak, dft


AMPS = 0.01 * jnp.concatenate([jnp.zeros((1, len(ORDERS))), jnp.eye(len(ORDERS))])


def _simulated_ripple(name):
    """The closed loop with FOC (`simulate`, speed imposed, current control at
    `I_DQ`), one run per order (vmapped over the harmonic amplitudes)."""
    obs = make_observer(name, DRIVE)
    x0 = obs.designed_error(OP, PLANT)
    foc = pj.FOC.from_drive(DRIVE)
    sc = pj.Scenario(t_end=N_STEPS * T_S, w_m_imposed=pj.Profile.constant(W),
                     i_d_ref=pj.Profile.constant(I_DQ[0]),
                     i_q_ref=pj.Profile.constant(I_DQ[1]))

    def one(amp):
        tr = pj.simulate(_with_harmonics(DRIVE, amp), foc, obs, sc, T_s=T_S, w_m0=W,
                         theta_hat0=-x0[obs.coordinates.angle], w_hat0=W,
                         i_dq0=tuple(I_DQ), throw=False)
        return tr.t, tr.theta_err

    t, err = jax.vmap(one)(AMPS)
    return _ripple(t[0], err, W)


def _ideal_current_ripple(obs, drive, w, n_steps, phases=(0.0,)):
    """Exact ideal current control at zero current: the voltage that holds the plant's
    current at zero is its PM back-EMF (harmonics included) averaged over each period;
    `run_plant` (speed imposed) confirms the current stays at zero, and the observer
    runs on the plant's voltage and current (`replay`). One run per order and harmonic
    phase (rad, `phases`), vmapped."""
    plant = drive.three_phase_motor
    x0 = obs.designed_error(analysis.OperatingPoint(w, jnp.zeros(2)), plant)
    t = jnp.arange(n_steps) * T_S
    th = w * jnp.arange(n_steps + 1) * T_S
    n_ph = len(phases)
    amps = jnp.concatenate([AMPS[:1], jnp.tile(AMPS[1:], (n_ph, 1))])
    phs = jnp.concatenate([jnp.zeros(1), jnp.repeat(jnp.asarray(phases), len(ORDERS))])

    def one(amp, phase):
        drv = _with_harmonics(drive, amp, phase)
        psi = jax.vmap(lambda q: pj.rotate(drv.motor.psi_pm_dq(q), q))(th)
        u = (psi[1:] - psi[:-1]) / T_S
        tr = pj.run_plant(drv, t, u, w_m_imposed=jnp.full(n_steps, w), w_m0=w)
        th_hat, _ = pj.replay(obs, t, u, tr.i_ab, theta0=-x0[obs.coordinates.angle], w0=w)
        return pj.wrap_angle(th[:-1] - th_hat), jnp.max(jnp.abs(tr.i_ab))

    err, i_max = jax.vmap(one)(amps, phs)
    # the held voltage matches the flux increment, not the back-EMF within the period:
    # the sampled current stays below 0.1 % of the base current
    assert float(jnp.max(i_max)) < 1e-3 * float(drive.base.I_b)
    peak, dft = _ripple(t, err, w)
    return peak.reshape(n_ph, len(ORDERS)), dft.reshape(n_ph, len(ORDERS))


def test_standstill_vmap_and_float32():
    obs = make_observer("leso", DRIVE)
    ws = jnp.array([0.0, 0.3, -0.5]) * DRIVE.w_rated
    ops = analysis.OperatingPoint(ws, jnp.broadcast_to(jnp.asarray(I_DQ), (3, 2)))
    r = jax.vmap(lambda op: analysis.harmonic_ripple(obs, DRIVE, op, (1, -5, 7)))(ops)
    assert r.shape == (3, 3) and bool(jnp.all(jnp.isfinite(r)))
    np.testing.assert_array_equal(np.asarray(r[0]), 0.0)  # no back-EMF at standstill
    assert bool(jnp.all(r[1:] > 0))
    # float32 follows the operating point's dtype and agrees
    d32, o32 = pj.astype(DRIVE, jnp.float32), pj.astype(obs, jnp.float32)
    op32 = analysis.OperatingPoint(jnp.float32(ws[1]), jnp.asarray(I_DQ, jnp.float32))
    r32 = analysis.harmonic_ripple(o32, d32, op32, (1, -5, 7))
    assert r32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(r32), np.asarray(r[1]), rtol=2e-3)


def test_order_one_is_the_static_error_of_a_flux_error():
    """Order 1: the angle offset of a 1 % PM-flux error, against the equilibria of the
    full error dynamics with the plant's psi_f above the observer's (small-signal: a
    0.01 % error, scaled; at 1 % the LESO's offset is 12 % below the linear value)."""
    obs = make_observer("leso", DRIVE)
    rip = float(analysis.harmonic_ripple(obs, DRIVE, OP, (1, -5, 7))[0])
    eps = 1e-4
    wrong = obs.with_motor(eqx.tree_at(lambda m: m.psi_f, obs.motor,
                                       PLANT.psi_f / (1 + eps)))
    offsets = []
    for o in (obs, wrong):
        eq = analysis.equilibria(o, PLANT, W, I_DQ)
        offsets.append(float(eq.theta[int(eq.principal)]))
    assert rip == pytest.approx(math.degrees(abs(offsets[1] - offsets[0])) * 0.01 / eps,
                                rel=0.01)


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
    """Closed loop with FOC at load. Tolerances: the discrete variant at the run's T_s
    within 2 % (1 % harmonics: the second-order terms are ~1 % of the first-order ones;
    the current loop is not ideal); the continuous linearisation within 10 % (the
    sampled observer differs by O(Omega T_s / 2), ~3 % at 6 w here)."""
    obs = make_observer(name, DRIVE)
    peak, dft = _simulated_ripple(name)
    disc = np.asarray(analysis.harmonic_ripple(obs, DRIVE, OP, ORDERS, T_s=T_S))
    cont = np.asarray(analysis.harmonic_ripple(obs, DRIVE, OP, ORDERS))
    print(name, "simulated peak", peak, "dft", dft, "discrete", disc, "continuous", cont)
    # the ripple is a sinusoid at (h - 1) w: its peak is its amplitude
    np.testing.assert_allclose(peak, dft, rtol=0.02)
    np.testing.assert_allclose(disc, peak, rtol=0.02)
    np.testing.assert_allclose(cont, peak, rtol=0.1)


@pytest.mark.parametrize("name", ["parallel-model", "fa-leso"])
def test_ripple_matches_the_plant_under_ideal_current_control(name):
    obs = make_observer(name, DRIVE)
    peak, dft = (v[0] for v in _ideal_current_ripple(obs, DRIVE, W, 1600))
    op = analysis.OperatingPoint(W, jnp.zeros(2))
    disc = np.asarray(analysis.harmonic_ripple(obs, DRIVE, op, ORDERS, T_s=T_S))
    cont = np.asarray(analysis.harmonic_ripple(obs, DRIVE, op, ORDERS))
    print(name, "simulated peak", peak, "dft", dft, "discrete", disc, "continuous", cont)
    np.testing.assert_allclose(disc, dft, rtol=0.01)
    np.testing.assert_allclose(disc, peak, rtol=0.02)
    np.testing.assert_allclose(cont, peak, rtol=0.1)  # O(Omega T_s / 2), as above


def test_rotor_flux_ripple_has_the_sidebands_of_its_periodic_error_dynamics():
    """The rotor-flux observer's error dynamics depend on the rotor angle (a 4 theta
    term in its linearisation): a harmonic at (h - 1) w also drives sidebands at
    (h - 1 +- 4) w, and the peak depends on the harmonic's phase. The harmonic balance
    of `harmonic_ripple` gives the worst case over that phase; the averaged
    linearisation (`T_s` variant) only the component at (h - 1) w."""
    drive = pj.preset("morawiec_ipm3k5")
    obs = make_observer("rotor-flux", drive)
    w = 0.5 * drive.w_rated
    peak, dft = _ideal_current_ripple(obs, drive, w, 4000,
                                      np.linspace(0.0, 2 * math.pi, 6, endpoint=False))
    op = analysis.OperatingPoint(w, jnp.zeros(2))
    worst = np.asarray(analysis.harmonic_ripple(obs, drive, op, ORDERS))
    disc = np.asarray(analysis.harmonic_ripple(obs, drive, op, ORDERS, T_s=T_S))
    print("rotor-flux simulated peak over phases", peak.max(0), "dft", dft.max(0),
          "harmonic balance", worst, "averaged (discrete)", disc)
    np.testing.assert_allclose(disc, dft.max(0), rtol=0.01)
    # continuous harmonic balance vs the sampled observer: O(Omega T_s / 2) as above, with
    # Omega up to (h - 1 + 4) w for the sidebands (~5 % here)
    np.testing.assert_allclose(worst, peak.max(0), rtol=0.06)


def test_response_command_reports_the_ripple_for_every_observer(capsys):
    import json

    from pmsmjax.cli.__main__ import main

    # a zhang2022 flux observer (no back-EMF estimate): the ripple only
    assert main(["response", "--motor", "zhang750", "--observer", "leso", "--speed", "0.5",
                 "--i-d", "0", "--i-q", "0.3", "--orders", "1", "-5", "7", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    want = analysis.harmonic_ripple(make_observer("leso", DRIVE), DRIVE, OP, (1, -5, 7))
    assert [o["order"] for o in rep["orders"]] == [1, -5, 7]
    for o, r in zip(rep["orders"], np.asarray(want)):
        assert o["angle_ripple_deg_per_pct"] == pytest.approx(float(r), rel=1e-9)
        assert "bemf_gain" not in o
        assert o["rotor_frame_frequency_hz"] == pytest.approx(
            (o["order"] - 1) * W / (2 * math.pi))
    # a back-EMF observer: the ripple next to the back-EMF gain, in the table too
    assert main(["response", "--motor", "zhang750", "--observer", "fa-leso", "--speed",
                 "0.5", "--i-d", "0", "--i-q", "0", "--orders", "-5", "7", "13"]) == 0
    out = capsys.readouterr().out
    assert "ripple (deg/%)" in out and "|G|" in out
    obs = make_observer("fa-leso", DRIVE)
    want = analysis.harmonic_ripple(obs, DRIVE, analysis.OperatingPoint(W, jnp.zeros(2)),
                                    ORDERS)
    gains = analysis.bemf_response(obs, W, ORDERS, 1e-4)
    rows = [line.split() for line in out.splitlines()[2:]]
    assert [int(r[0]) for r in rows] == list(ORDERS)
    for r, rip, g in zip(rows, np.asarray(want), gains):
        assert float(r[2]) == pytest.approx(float(rip), abs=1e-5)
        assert float(r[3]) == pytest.approx(abs(g), abs=1e-5)


@pytest.mark.parametrize("name", sorted(pj.observers.observer_names()))
def test_angle_dependent_flag_tells_whether_the_error_dynamics_depend_on_the_angle(name):
    """`angle_dependent` (the contract's class flag) is what `harmonic_ripple` trusts to
    evaluate the linearisation at one angle: check it against `error_rhs` itself."""
    drive = pj.preset("morawiec_ipm3k5") if name == "rotor-flux" else DRIVE
    obs = make_observer(name, drive)
    plant = drive.three_phase_motor
    op = analysis.OperatingPoint(0.5 * drive.w_rated, jnp.asarray(I_DQ))
    x0 = obs.designed_error(op, plant)

    # the Jacobian at three angles in one compiled program (op by op, each of its many
    # small operations would compile on its own)
    @jax.jit
    @jax.vmap
    def jacobian(theta):
        return jax.jacfwd(lambda x: obs.error_rhs(
            x, analysis.OperatingPoint(op.w_m, op.i_dq, theta), plant))(x0)

    A = list(np.asarray(jacobian(jnp.array([0.0, 0.7, 2.1]))))
    same = all(np.allclose(a, A[0], rtol=1e-9, atol=1e-9 * np.abs(A[0]).max()) for a in A)
    assert same != obs.angle_dependent


# the one-angle shortcut is the same code for every observer: the LESO checks it in the fast
# suite (its one-angle ripple, continuous and discrete, at three orders, is the program the
# tests above compiled), the FA-LESO (its discrete step compiles for 25 s) only in the slow one
@pytest.mark.parametrize("name", ["leso", pytest.param("fa-leso", marks=pytest.mark.slow)])
def test_one_angle_for_angle_independent_observers_equals_the_full_balance(name):
    """An observer whose error dynamics do not depend on the angle is evaluated at one
    angle; the 16-angle harmonic balance (forced by a subclass that declares
    `angle_dependent`) gives the same ripple, continuous and discrete."""
    obs = make_observer(name, DRIVE)
    assert not obs.angle_dependent

    class Forced(type(obs)):
        angle_dependent = True

    forced = copy.copy(obs)
    object.__setattr__(forced, "__class__", Forced)
    assert forced.angle_dependent
    orders = (1, -5, 7)  # order 1 (a fixed phase) and two harmonics
    for T_s in (None, T_S):
        one = np.asarray(analysis.harmonic_ripple(obs, DRIVE, OP, orders, T_s=T_s))
        full = np.asarray(analysis.harmonic_ripple(forced, DRIVE, OP, orders, T_s=T_s))
        np.testing.assert_allclose(one, full, rtol=1e-11, atol=1e-12 * np.abs(full).max())
