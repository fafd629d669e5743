"""The rotor-flux observer's design in physical terms (pmsmjax.observers._rotor_flux_design):
the first-order reduction of its spectrum against the full linearisation, the speed
below which its speed law damps itself, the speed-law bandwidth on the salient paper
machine, and the tuner's coordinates built from them."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmsmjax as pj
import tuning as tg
from pmsmjax import analysis
from pmsmjax.observers import RotorFluxObserver, make_observer
from pmsmjax.observers._rotor_flux_design import reduced_poles, self_damped_below


IPM = pj.preset("morawiec_ipm3k5")
ROUND = pj.replace_params(IPM, L_d=IPM.motor.L_q)  # non-salient: L_d = L_q
C_ALPHA = 3.0  # the paper's


def _slow_pair(obs, drive, w, i_q_pu=0.3):
    """The two eigenvalues of smallest modulus of the linearised error dynamics
    (averaged over the rotor angle) at electrical speed `w` (rad/s)."""
    i = jnp.array([0.0, i_q_pu * float(drive.base.I_b)])
    ev = np.linalg.eigvals(np.asarray(analysis.linearization(obs, drive.three_phase_motor,
                                                             w, i)))
    return ev[np.argsort(np.abs(ev))][:2]


def _round_observer(w, k_c):
    """The paper's c_alpha on the non-salient variant, w_gamma at 0.15 |a + j w| (inside
    the quasi-static step's range), no c_lambda term (the reduction has none)."""
    m = ROUND.three_phase_motor
    a = (1.0 + C_ALPHA) * m.R_s / m.L_q
    design = RotorFluxObserver.design_from_tuning(
        {"w_gamma": 0.15 * math.hypot(a, w), "a_i": a}, ROUND)
    obs = make_observer("rotor-flux", ROUND).with_design(
        c_lambda=0.0, k_c=k_c, **{k: float(v) for k, v in design.items()})
    return obs, float(design["gamma"])


@pytest.mark.parametrize("k_c", [0.0, 0.1, 0.3])
def test_first_order_reduction_is_the_linearised_slow_pair_and_its_damping_limit(k_c):
    """The reduction m s^2 + c_1 s + c_0 against `analysis.linearization` of the
    observer that runs (non-salient, where the position correction carries nothing):
    measured |d Im| / Im <= 0.006 and |d Re| / |lambda| <= 0.0011 at 0.3, 0.6, 1.0 p.u.
    (tested at 3x); the quasi-static step alone gets the real part wrong in sign above the
    derived speed. That speed, a (sqrt(1 + k_c^2) - k_c), is where the real part of the
    slow pair changes sign: negative at 0.9x it, positive at 1.1x."""
    m = ROUND.three_phase_motor
    w_rated = float(ROUND.w_rated)
    w_b = float(self_damped_below(C_ALPHA, k_c, m))
    for w in (0.3 * w_rated, 0.6 * w_rated, w_rated):
        obs, gamma = _round_observer(w, k_c)
        full = np.sort_complex(_slow_pair(obs, ROUND, w))[1]
        red = np.sort_complex(np.asarray(reduced_poles(gamma, C_ALPHA, k_c, m, w)))[1]
        assert abs(full.imag - red.imag) < 0.018 * abs(red.imag), (w, full, red)
        assert abs(full.real - red.real) < 0.0035 * abs(red), (w, full, red)
        a = (1.0 + C_ALPHA) * m.R_s / m.L_q
        if w > w_b and a > k_c * w:  # the quasi-static damping k (a - k_c |w|) > 0 here
            assert full.real > 0, (w, full)
    for factor, sign in ((0.9, -1.0), (1.1, 1.0)):
        w = factor * w_b
        obs, _ = _round_observer(w, k_c)
        assert sign * float(np.max(_slow_pair(obs, ROUND, w).real)) > 0, (factor, w)


def test_w_gamma_is_the_speed_law_bandwidth_on_the_salient_paper_machine():
    """morawiec_ipm3k5 (L_q = 2.9 L_d) with the paper's gains and gamma lowered to
    w_gamma = 35 and 100 rad/s (quasi-static range), no load: sqrt(|l1 l2|) of the slow
    pair is w_gamma = sqrt(gamma) psi_f / L_q; measured within 0.72 % at 0.5 and 1 p.u.
    (tested at 3x). With L_d in its place it would be 2.9 times too large."""
    paper = make_observer("rotor-flux", IPM)
    own = RotorFluxObserver.tuning_from_design(
        {k: float(v) for k, v in paper.design_parameters().items()}, IPM)
    for w_gamma in (35.0, 100.0):
        obs = paper.with_design(**{k: float(v) for k, v in RotorFluxObserver.design_from_tuning(
            own | {"w_gamma": w_gamma}, IPM).items() if k == "gamma"})
        for speed in (0.5, 1.0):
            l1, l2 = _slow_pair(obs, IPM, speed * float(IPM.w_rated), i_q_pu=0.0)
            assert abs(math.sqrt(abs(l1 * l2)) / w_gamma - 1) < 0.022, (w_gamma, speed, l1, l2)


def test_the_tuner_searches_the_rotor_flux_observer_in_physical_terms(monkeypatch):
    """The coordinates, their kinds and the paper's values; the bounds from the rules,
    narrowed to where the linearised error dynamics stay stable over the drive's
    operating points: checked here point by point with NumPy's eigenvalues, at each bound
    (stable everywhere) and one scan step beyond it where the scan stopped (unstable
    somewhere)."""
    problem = tg.TuningProblem.quick(observer="rotor-flux")
    space = tg.DesignSpace(problem)
    c = {x.name: x for x in space.coordinates}
    assert {k: x.kind for k, x in c.items()} == {
        "w_gamma": "tracking", "a_i": "explicit", "c_theta": "explicit", "k_c": "contract"}
    m, paper = IPM.three_phase_motor, make_observer("rotor-flux", IPM)
    assert math.isclose(c["w_gamma"].paper, math.sqrt(float(paper.gamma)) * m.psi_f / m.L_q,
                        rel_tol=1e-12)
    assert math.isclose(c["a_i"].paper, (1 + float(paper.c_alpha)) * m.R_s / m.L_d,
                        rel_tol=1e-12)
    d = space.design(space.paper_point())
    for k in ("gamma", "c_alpha", "c_theta", "k_c"):
        assert math.isclose(float(d[k]), float(getattr(paper, k)), rel_tol=1e-12), k
    with monkeypatch.context() as patch:  # the rules' bounds, before the spectrum
        patch.setattr(RotorFluxObserver, "tuning_spectral", False)
        rules = {x.name: (x.lo, x.hi) for x in tg.DesignSpace(problem).coordinates}
    assert rules["w_gamma"] == space.w_track and rules["k_c"] == pytest.approx((0.01, 1.0))
    step = {k: (hi / lo) ** (1 / (tg.design_space.SPECTRUM_SCAN - 1))
            for k, (lo, hi) in rules.items()}
    x0 = space.paper_point()
    speeds = np.array(tg.design_space.SPECTRUM_SPEEDS_PU) * float(IPM.w_rated)
    currents = np.array(tg.design_space.SPECTRUM_IQ_PU) * float(IPM.base.I_b)

    def max_real(j, value):
        x = x0.copy()
        x[j] = value
        obs = space.observer(x)
        return max(float(np.max(np.linalg.eigvals(np.asarray(analysis.linearization(
            obs, m, w, jnp.array([float(pj.mtpa_i_d(i_q, m)), i_q])))).real))
            for w in speeds for i_q in currents)

    narrowed = 0
    for j, name in enumerate(space.names):
        lo, hi = c[name].lo, c[name].hi
        assert rules[name][0] * (1 - 1e-9) <= lo < c[name].paper < hi <= rules[name][1] * (
            1 + 1e-9), name
        for bound, beyond, inside in ((lo, lo / step[name], lo > rules[name][0] * 1.001),
                                      (hi, hi * step[name], hi < rules[name][1] * 0.999)):
            assert max_real(j, bound) < 0, (name, bound)
            if inside:  # the scan stopped here: its next value is unstable
                narrowed += 1
                assert max_real(j, beyond) > 0, (name, beyond)
    assert narrowed >= 3  # measured: w_gamma's lower, a_i's, c_theta's and k_c's upper
    # the comparison job builds the space while it traces its runs: the same bounds
    traced = []
    jax.jit(lambda v: traced.append(tg.DesignSpace(problem).coordinates) or v)(0.0)
    assert traced == [space.coordinates]
    with pytest.raises(ValueError, match="pass `drive=`"):
        RotorFluxObserver.design_from_tuning({"w_gamma": 100.0, "a_i": 50.0})


def test_a_paper_design_unstable_on_the_grid_keeps_the_rules_bounds(monkeypatch):
    """Below about 0.13 p.u. at light load no rotor-flux design is stable (its module
    docstring): with 0.05 p.u. in the grid the paper's design is not stable there, and
    every coordinate keeps the bounds of its rule, saying why."""
    problem = tg.TuningProblem.quick(observer="rotor-flux")
    with monkeypatch.context() as patch:
        patch.setattr(RotorFluxObserver, "tuning_spectral", False)
        rules = tg.DesignSpace(problem).coordinates
    monkeypatch.setattr(tg.design_space, "SPECTRUM_SPEEDS_PU", (0.05, 0.5))
    kept = tg.DesignSpace(problem).coordinates
    assert [(c.lo, c.hi) for c in kept] == [(c.lo, c.hi) for c in rules]
    assert all(c.why.endswith("p.u. (MTPA): bounds kept") and "not stable" in c.why
               for c in kept)
