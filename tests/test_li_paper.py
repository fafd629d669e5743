"""li-fa-leso's experiments (`pmsmjax.papers.li`): harmonic content of the estimated
back-EMF against the frequency response (individual sets and VSD), and the parameter-
mismatch offsets: exact formula vs the equilibrium of the error dynamics vs closed-loop
simulation, and the printed (42)-(43) shown to hold only approximately."""

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax.observers import OperatingPoint, make_observer
from pmsmjax.papers import li


DTP = pj.preset("li_dtp")
PLANT = DTP.three_phase_motor


def test_individual_set_harmonics_follow_the_frequency_response():
    """Fig. 13 (300 rpm, half load): the C-LESO on set 1; the 5th and 7th of the
    estimated alpha back-EMF are |G_h| a_h / |G_1| of the assumed harmonics."""
    out = li.harmonics("c-leso", 300, 0.5, "sets", t_end=0.4)
    # measured: the 5th 0.15 % from the linear response, the 7th 2.6 % (3.8 % at a
    # quarter of the sampling period, so not the discretisation; a coupling between the
    # -5th and 7th, both at 6 w in the rotor frame, is the likely cause, not yet shown);
    # allow about twice each
    assert out["simulated_pct"][5] == pytest.approx(out["response_pct"][5], rel=0.005)
    assert out["simulated_pct"][7] == pytest.approx(out["response_pct"][7], rel=0.05)
    # the C-LESO passes most of the 5th (3 % assumed)
    assert out["simulated_pct"][5] > 2.0


def test_vsd_control_keeps_the_5th_and_7th_out_of_the_alpha_beta_observer():
    """Fig. 15: with the dual machine the plant maps the 5th and 7th to the x-y subspace."""
    out = li.harmonics("c-leso", 600, 0.8, "vsd", t_end=0.3)
    assert max(out["simulated_pct"].values()) < 1e-3
    # ... and the x-y currents, which the x-y controller regulates to zero (without it
    # they are ~1 A rms here, see tests/test_dtp_control.py)
    assert out["i_xy_rms"] < 1e-3


@pytest.mark.parametrize("param, ratio, i_pu", [("L_q", 1.5, (-0.5, 1.0)),
                                                 ("R_s", 0.5, (-0.5, 1.0))])
def test_mismatch_offset_exact_vs_equilibrium_vs_simulation(param, ratio, i_pu):
    w = li.rpm_to_w(DTP, 300)
    i = np.asarray(i_pu) * float(DTP.base.I_b)
    model = eqx.tree_at(lambda m: getattr(m, param), PLANT, float(getattr(PLANT, param)) * ratio)
    exact = li.mismatch_offset(PLANT, model, w, i)
    obs = make_observer("fa-leso", DTP, motor=model)
    x = obs.designed_error(OperatingPoint(w, jnp.asarray(i)), PLANT)
    assert float(x[obs.coordinates.angle]) == pytest.approx(exact, abs=1e-9)
    eq = pj.analysis.equilibria(obs, PLANT, w, i)
    th = np.asarray(eq.theta)[np.asarray(eq.valid) & np.asarray(eq.stable)]
    assert np.min(np.abs(th - exact)) < 1e-7
    # closed loop (current control at an imposed speed, i_d = -0.5 p.u.)
    foc = pj.FOC.from_drive(DTP)
    sc = pj.Scenario(t_end=0.3, w_m_imposed=pj.Profile.constant(w),
                     i_d_ref=pj.Profile.constant(i[0]), i_q_ref=pj.Profile.constant(i[1]))
    traj = pj.simulate(DTP, foc, obs, sc, T_s=li.T_S, w_m0=w)
    sim = float(np.mean(np.asarray(traj.theta_err)[-1000:]))
    assert sim == pytest.approx(exact, abs=math.radians(0.05))
    printed = li.mismatch_offset_printed(PLANT, model, w, i, param)
    assert abs(printed - exact) > math.radians(0.05)  # (42)-(43) are approximations


def test_printed_formulas_hold_at_zero_d_current_for_r_s_only():
    rows = li.mismatch_table(i_dq_pu=((0.0, 1.0),), ratios=(0.5, 1.5))
    for r in rows:
        assert r["exact_deg"] == pytest.approx(r["equilibrium_deg"], abs=1e-6)
        if r["param"] == "R_s":
            assert abs(r["exact_deg"]) < 1e-9 and abs(r["printed_deg"]) < 1e-9
        else:
            assert 0.1 < abs(r["printed_deg"] - r["exact_deg"]) < 1.0
            assert np.sign(r["printed_deg"]) == np.sign(r["exact_deg"]) == np.sign(r["ratio"] - 1)
