"""Dual three-phase current control in the closed loop (`FOC.from_drive(dual=...)`):
VSD control with the x-y currents regulated, and two individual sets, on `li_dtp` (5th
and 7th back-EMF harmonics, which the winding maps to the x-y subspace).

Runs at an imposed rated speed (50 Hz electrical: one period is 200 samples at
T_s = 100 us), current control, sensored; the last electrical period is analysed.
"""

import math

import numpy as np
import pytest

import pmsmjax as pj


T_S = 1e-4
DRIVE = pj.preset("li_dtp")
W = float(DRIVE.w_rated)
N_PER = int(round(2 * math.pi / W / T_S))  # samples per electrical period (200)
I_Q = 4.0
I_XY_REF = (1.0, -0.5)
# individual sets: the differential mode is 3.5-5.5x faster than alpha_c (see
# pmsmjax.DualCurrentControl); a lower alpha_c keeps its discrete loop well damped
ALPHA_IND = 2 * math.pi * 100


def _conj(v):
    return np.stack([v[..., 0], -v[..., 1]], -1)


def _rot(v, ang):
    c, s = np.cos(ang), np.sin(ang)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], -1)


@pytest.fixture(scope="module")
def runs():
    assert N_PER == 200
    sc = pj.Scenario(t_end=0.1, w_m_imposed=pj.Profile.constant(W),
                     i_d_ref=pj.Profile.constant(0.0), i_q_ref=pj.Profile.constant(I_Q))
    focs = {
        "none": pj.FOC.from_drive(DRIVE),
        "vsd": pj.FOC.from_drive(DRIVE, dual="vsd"),
        "pi_only": pj.FOC.from_drive(DRIVE, dual="vsd", alpha_r=0.0),
        "vsd_ref": pj.FOC.from_drive(DRIVE, dual="vsd", i_xy_ref=I_XY_REF),
        "individual": pj.FOC.from_drive(DRIVE, dual="individual", alpha_c=ALPHA_IND),
    }
    out = {}
    for name, foc in focs.items():
        tr = pj.simulate(DRIVE, foc, pj.observers.SensoredObserver(), sc, T_s=T_S, w_m0=W)
        last = slice(-N_PER, None)
        out[name] = {k: np.asarray(getattr(tr, k)[last])
                     for k in ("theta", "i_dq", "i_ab", "i_xy", "u_xy", "tau_M", "tau_ref")}
    return out


def _rms(v):
    return float(np.sqrt(np.mean(np.sum(v ** 2, -1))))


def _anti_sync(r):
    """The x-y current in the anti-synchronous frame (at -theta)."""
    return _rot(r["i_xy"], r["theta"])


def _spectrum(z):
    """Complex Fourier coefficients over one electrical period: entry k is the amplitude
    of exp(j k theta)."""
    return np.fft.fft(z) / len(z)


def test_set_vectors_match_vsd_matrix():
    """i_ab = (i_1 + i_2)/2, i_xy = conj(i_1 - i_2)/2 for the sets' space vectors (common
    stationary frame), as `DualCurrentControl` uses them."""
    rng = np.random.default_rng(0)
    i1, i2 = rng.normal(size=(2, 2))
    ang = np.array([0, 2, 4]) * np.pi / 3
    gamma = float(DRIVE.motor.gamma)
    ph1 = i1[0] * np.cos(ang) + i1[1] * np.sin(ang)
    ph2 = i2[0] * np.cos(ang + gamma) + i2[1] * np.sin(ang + gamma)
    i_ab, i_xy, _ = (np.asarray(a) for a in pj.vsd(np.r_[ph1, ph2]))
    np.testing.assert_allclose(i_ab, 0.5 * (i1 + i2), atol=1e-12)
    np.testing.assert_allclose(i_xy, 0.5 * _conj(i1 - i2), atol=1e-12)


def test_xy_harmonics_without_control_are_5th_and_minus_7th(runs):
    """No x-y control: the x-y current is the 5th (exp(+j5 theta)) and 7th
    (exp(-j7 theta)) harmonic, i.e. +-6th in the anti-synchronous frame; nothing constant."""
    r = runs["none"]
    z = r["i_xy"][:, 0] + 1j * r["i_xy"][:, 1]
    Z = _spectrum(z)  # stationary x-y
    total = _rms(r["i_xy"])
    assert total > 0.5  # ~1.27 A rms
    assert math.hypot(abs(Z[5]), abs(Z[-7])) == pytest.approx(total, rel=1e-3)
    za = _anti_sync(r)
    Za = _spectrum(za[:, 0] + 1j * za[:, 1])
    assert math.hypot(abs(Za[6]), abs(Za[-6])) == pytest.approx(total, rel=1e-3)
    assert abs(Za[0]) < 1e-3 * total


def test_vsd_xy_regulated_to_zero(runs):
    none, vsd = runs["none"], runs["vsd"]
    assert _rms(vsd["i_xy"]) < 1e-4 * _rms(none["i_xy"])
    assert _rms(vsd["u_xy"]) > 1.0  # the controller cancels the harmonic back-EMF
    assert np.all(none["u_xy"] == 0.0)
    # alpha-beta unaffected: the same d-q currents
    np.testing.assert_allclose(vsd["i_dq"].mean(0), [0.0, I_Q], atol=1e-3)


def test_anti_synchronous_pi_alone_leaves_the_harmonics(runs):
    """Without the harmonic integrators (alpha_r = 0) the PI in the anti-synchronous frame
    (pole-cancelling, bandwidth alpha_xy) only divides each harmonic: the x-y plant with
    decoupling is L s + R there, the harmonic sits at s = +-j6w, so in continuous time
    |I_h| = |E_h| |s| / |(L s + R)(s + alpha_xy)|, with |E_h| = |I_h,none| |R + j h w L|
    from the uncontrolled run. (The simulation is 5-8 % above: sampling and delay.)"""
    R, L = float(DRIVE.motor.ab.R_s), float(DRIVE.motor.L_xy)
    alpha = 2 * math.pi * 500.0  # FOC.from_drive's default alpha_c = alpha_xy

    def coef(name, k):
        z = runs[name]["i_xy"]
        return abs(_spectrum(z[:, 0] + 1j * z[:, 1])[k])

    for h, k in ((5, 6), (7, -6)):
        bin_ = 5 if h == 5 else -7  # exp(+j5 theta), exp(-j7 theta) in stationary x-y
        E = coef("none", bin_) * abs(R + 1j * h * W * L)
        s = 1j * k * W
        predicted = E * abs(s) / abs((R + L * s) * (s + alpha))
        assert coef("pi_only", bin_) == pytest.approx(predicted, rel=0.1)
        assert coef("pi_only", bin_) > 0.3 * coef("none", bin_)


def test_vsd_xy_follows_constant_reference(runs):
    """A constant reference in the anti-synchronous frame (unequal set currents) is held,
    and the harmonics are still removed."""
    za = _anti_sync(runs["vsd_ref"])
    np.testing.assert_allclose(za.mean(0), I_XY_REF, atol=1e-4)
    assert _rms(za - za.mean(0)) < 1e-4 * _rms(runs["none"]["i_xy"])


def _set_currents(r):
    """Each set's current in its own rotor frame, from the plant's VSD state through
    `pmsmjax.inv_vsd` (phases) and each set's own Clarke transform (set 2 at theta -
    gamma)."""
    ph = np.asarray(pj.inv_vsd(r["i_ab"], r["i_xy"]))
    gamma = float(DRIVE.motor.gamma)
    i1 = _rot(np.asarray(pj.clarke(ph[:, :3])), -r["theta"])
    i2 = _rot(np.asarray(pj.clarke(ph[:, 3:])), -(r["theta"] - gamma))
    return ph, i1, i2


def test_individual_sets_follow_references(runs):
    r = runs["individual"]
    _, i1, i2 = _set_currents(r)
    for i in (i1, i2):
        np.testing.assert_allclose(i.mean(0), [0.0, I_Q], atol=2e-3)
    # ... and the set currents are the ones the controller forms from the VSD state
    np.testing.assert_allclose(_rot(i1, r["theta"]), r["i_ab"] + _conj(r["i_xy"]),
                               atol=1e-9)


def test_individual_torque_matches_vsd(runs):
    ind, vsd = runs["individual"], runs["vsd"]
    np.testing.assert_allclose(ind["tau_ref"], vsd["tau_ref"], rtol=1e-12)
    assert ind["tau_M"].mean() == pytest.approx(vsd["tau_M"].mean(), rel=1e-2)
    assert vsd["tau_M"].mean() == pytest.approx(vsd["tau_ref"].mean(), rel=1e-4)


def test_harmonics_land_where_the_winding_puts_them(runs):
    """5th/7th in the phase currents: in x-y (none) or in each set (individual); VSD
    control with x-y regulation removes them from the phases. Alpha-beta never has them."""
    amp = {}
    for name in ("none", "vsd", "individual"):
        ph, _, _ = _set_currents(runs[name])
        A = _spectrum(ph[:, 0])  # phase a1
        amp[name] = 2 * math.hypot(abs(A[5]), abs(A[7]))
        i_dq = runs[name]["i_dq"]
        # d-q ripple: measured 9e-7 (none, vsd) and 3.1e-4 (individual: the sets'
        # controllers see the x-y harmonics) of the uncontrolled harmonic amplitude
        assert _rms(i_dq - i_dq.mean(0)) < 1e-3 * amp["none"]
    assert amp["none"] > 1.0
    assert amp["vsd"] < 1e-4 * amp["none"]
    assert 0.2 * amp["none"] < amp["individual"] < amp["none"]
    # individual: the per-set 5th/7th are the x-y harmonics (i_1 - i_ab = conj(i_xy))
    # (the phase amplitude sqrt(|I_5|^2 + |I_7|^2) is the rms of the x-y vector)
    # (measured 1.2e-4 relative: the spectrum's two bins against the whole rms, which
    # also holds the small other harmonics of the closed loop)
    assert _rms(runs["individual"]["i_xy"]) == pytest.approx(amp["individual"], rel=5e-4)


def test_dual_control_needs_a_dual_drive():
    with pytest.raises(ValueError, match="dual"):
        pj.FOC.from_drive(pj.preset("zhang750"), dual="vsd")
    with pytest.raises(ValueError, match="'vsd' or 'individual'"):
        pj.FOC.from_drive(DRIVE, dual="sets")
    foc = pj.FOC.from_drive(DRIVE, dual="vsd")
    sc = pj.Scenario(t_end=0.01, w_m_ref=pj.Profile.constant(0.0))
    with pytest.raises(ValueError, match="three-phase"):
        pj.simulate(pj.preset("zhang750"), foc, pj.observers.SensoredObserver(), sc)


def test_dual_control_float32():
    """A single-precision run keeps its dtype (x-y state and output included)."""
    import jax.numpy as jnp

    sc = pj.Scenario(t_end=0.03, w_m_imposed=pj.Profile.constant(W),
                     i_d_ref=pj.Profile.constant(0.0), i_q_ref=pj.Profile.constant(I_Q))
    d32 = pj.astype(DRIVE, jnp.float32)
    foc = pj.astype(pj.FOC.from_drive(DRIVE, dual="vsd"), jnp.float32)
    tr = pj.simulate(d32, foc, pj.observers.SensoredObserver(), sc, T_s=T_S, w_m0=W)
    assert tr.i_xy.dtype == tr.u_xy.dtype == jnp.float32
    # the same run in double precision: the x-y currents agree to 1.4e-6 A and the
    # alpha-beta ones to 1.3e-5 A measured (float32's 6e-8 relative of 4 A, 2.4e-7 A, per
    # step, which the current loops keep from accumulating far); allow 4 times that
    tr64 = pj.simulate(DRIVE, pj.FOC.from_drive(DRIVE, dual="vsd"),
                       pj.observers.SensoredObserver(), sc, T_s=T_S, w_m0=W)
    np.testing.assert_allclose(np.asarray(tr.i_xy, float), tr64.i_xy, rtol=0, atol=6e-6)
    np.testing.assert_allclose(np.asarray(tr.i_ab, float), tr64.i_ab, rtol=0, atol=5e-5)
    # after 25 ms the x-y rms is ~5e-4 A (the harmonic integrators still converging; 1.3
    # A unregulated)
    assert _rms(np.asarray(tr.i_xy[-N_PER // 2:])) < 1e-3
