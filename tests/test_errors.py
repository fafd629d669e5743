"""Bad inputs raise `ValueError` with a message that names the argument."""

import math
import re

import numpy as np
import pytest

import pmsmjax as pj


DRIVE = pj.preset("zhang750")
MOTOR = dict(R_s=0.78, L_d=2.46e-3, L_q=2.68e-3, psi_f=0.056, n_p=5.0)
SCENARIO = pj.Scenario(t_end=0.01, w_m_ref=pj.Profile.constant(100.0))


def _sim(**kw):
    args = dict(drive=DRIVE, controller=pj.FOC.from_drive(DRIVE),
                observer=pj.SensoredObserver(), scenario=SCENARIO)
    for k in list(args):
        if k in kw:
            args[k] = kw.pop(k)
    return pj.simulate(args["drive"], args["controller"], args["observer"],
                       args["scenario"], **kw)


def _raises(match):
    return pytest.raises(ValueError, match=re.escape(match))


# --------------------------------------------------------------------------------------
# Parameters
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["R_s", "L_d", "L_q"])
@pytest.mark.parametrize("value", [0.0, -1e-3, math.nan, math.inf])
def test_motor_parameters_positive(name, value):
    with _raises(f"PMSMParams({name}=...)"):
        pj.PMSMParams(**{**MOTOR, name: value})


@pytest.mark.parametrize("value", [-0.01, math.nan])
def test_psi_f_nonnegative(value):
    with _raises("PMSMParams(psi_f=...)"):
        pj.PMSMParams(**{**MOTOR, "psi_f": value})
    pj.PMSMParams(**{**MOTOR, "psi_f": 0.0})  # synchronous reluctance machine is fine


@pytest.mark.parametrize("value", [0.0, -1.0, math.nan])
def test_inertia_positive(value):
    with _raises("Mechanics(J=...)"):
        pj.Mechanics(J=value)
    with _raises("Mechanics(B=...)"):
        pj.Mechanics(J=1e-3, B=-1.0)


def test_dual_three_phase_L_xy():
    ab = pj.preset("li_dtp").motor.ab
    with _raises("DualThreePhaseParams(L_xy=...)"):
        pj.DualThreePhaseParams(ab=ab, L_xy=0.0)


def test_replace_params_validates():
    with _raises("PMSMParams(L_q=...)"):
        pj.replace_params(DRIVE, L_q=-1.0)
    with _raises("Mechanics(J=...)"):
        pj.replace_params(DRIVE, J=0.0)
    with _raises("'L_x'"):
        pj.replace_params(DRIVE, L_x=1.0)


def test_unknown_preset():
    with _raises("'zhang751'"):
        pj.preset("zhang751")
    with pytest.raises(ValueError, match="preset"):
        pj.preset("")


def test_inverter_limits():
    with _raises("Inverter(u_max=...)"):
        pj.Inverter(u_dc=300.0, u_max=200.0 + 1e-6)
    pj.Inverter(u_dc=300.0, u_max=200.0)  # six-step limit 2 u_dc / 3 is allowed
    with _raises("Inverter(u_dc=...)"):
        pj.Inverter(u_dc=-300.0)
    with _raises("Inverter(u_dc=...)"):
        pj.Inverter(u_dc=math.nan)


@pytest.mark.parametrize("order", [1, 0, (7, 1)])
def test_emf_harmonics_order(order):
    with _raises("EMFHarmonics(order=...)"):
        pj.EMFHarmonics(order=order, amplitude=np.full(np.size(order), 0.01))


def test_emf_harmonics_nan():
    with _raises("EMFHarmonics(amplitude=...)"):
        pj.EMFHarmonics(order=(-5,), amplitude=(math.nan,))
    with _raises("EMFHarmonics(phase=...)"):
        pj.EMFHarmonics(order=(-5,), amplitude=(0.01,), phase=(math.inf,))


def test_sensing():
    with _raises("Sensing(noise_std=...)"):
        pj.Sensing(noise_std=-0.1)
    with _raises("Sensing(delay=...)"):
        pj.Sensing(delay=-1)
    with _raises("Sensing(delay=...)"):
        pj.Sensing(delay=1.5)


def test_controller_parameters():
    with _raises("CurrentController(alpha_c=...)"):
        pj.FOC.from_drive(DRIVE, alpha_c=0.0)
    with _raises("SpeedController(alpha_s=...)"):
        pj.FOC.from_drive(DRIVE, alpha_s=-1.0)
    with _raises("CurrentRefs(strategy=...)"):
        pj.FOC.from_drive(DRIVE, strategy="fastest")


# --------------------------------------------------------------------------------------
# Profiles and scenarios
# --------------------------------------------------------------------------------------

def test_profile_empty():
    with _raises("Profile(t=...)"):
        pj.Profile([], [])


def test_profile_non_monotonic():
    with _raises("Profile(t=...)"):
        pj.Profile([0.0, 0.2, 0.1], [1.0, 2.0, 3.0])
    pj.Profile([0.0, 0.1, 0.1], [1.0, 1.0, 3.0])  # a repeated time is a step


def test_profile_shapes_and_nan():
    with _raises("Profile(t=..., v=...)"):
        pj.Profile([0.0, 1.0], [1.0])
    with _raises("Profile(v=...)"):
        pj.Profile([0.0, 1.0], [1.0, math.nan])
    with _raises("Profile(t=...)"):
        pj.Profile([0.0, math.nan], [1.0, 2.0])


def test_scenario_needs_references():
    with _raises("w_m_ref"):
        pj.Scenario(t_end=0.1)
    with _raises("i_q_ref"):
        pj.Scenario(t_end=0.1, i_d_ref=pj.Profile.constant(0.0))
    with _raises("Scenario(t_end=...)"):
        pj.Scenario(t_end=-0.1, w_m_ref=pj.Profile.constant(1.0))
    with _raises("Scenario(tau_L=...)"):
        pj.Scenario(t_end=0.1, w_m_ref=pj.Profile.constant(1.0), tau_L=2.0)


def test_scenario_scale_keys():
    with _raises("Scenario(plant_scale=...)"):
        pj.Scenario(t_end=0.1, w_m_ref=pj.Profile.constant(1.0),
                    plant_scale={"J": pj.Profile.constant(1.0)})
    with _raises("Scenario(observer_scale=...)"):
        pj.Scenario(t_end=0.1, w_m_ref=pj.Profile.constant(1.0),
                    observer_scale={"Rs": pj.Profile.constant(1.0)})
    with _raises("plant_scale['R_s']"):
        pj.Scenario(t_end=0.1, w_m_ref=pj.Profile.constant(1.0),
                    plant_scale={"R_s": pj.Profile.constant(0.0)})


# --------------------------------------------------------------------------------------
# simulate
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("T_s", [0.0, -1e-4, math.nan])
def test_simulate_T_s_positive(T_s):
    with _raises("simulate(T_s=...)"):
        _sim(T_s=T_s)


def test_simulate_T_s_too_long():
    # zhang750: fastest plant mode ~ hypot(R/L_d, 2 w_rated) = 2.5e3 1/s; RK4 is stable
    # for h |lambda| < 2.78, so T_s = 5 ms with one step cannot work.
    with _raises("`T_s=0.005` s is too long"):
        _sim(T_s=5e-3, n_substeps=1, scenario=pj.Scenario(
            t_end=0.05, w_m_ref=pj.Profile.constant(100.0)))
    with _raises("n_substeps"):
        _sim(n_substeps=0)


def test_simulate_save_every():
    with _raises("save_every"):
        _sim(save_every=7)  # 80 steps
    with _raises("save_every"):
        _sim(save_every=0)


def test_simulate_noise_needs_key():
    with _raises("key"):
        _sim(sensing=pj.Sensing(noise_std=0.05))


def test_simulate_bad_objects():
    with _raises("drive"):
        _sim(drive=DRIVE.motor)
    with _raises("observer"):
        _sim(observer=None)
    with _raises("t_end"):
        _sim(scenario=pj.Scenario(t_end=1e-5, w_m_ref=pj.Profile.constant(1.0)))


def test_observer_scale_needs_motor():
    sc = pj.Scenario(t_end=0.01, w_m_ref=pj.Profile.constant(100.0),
                     observer_scale={"R_s": pj.Profile.constant(1.1)})
    with _raises("observer_scale"):
        _sim(scenario=sc)


# --------------------------------------------------------------------------------------
# run_plant
# --------------------------------------------------------------------------------------

T_RP = np.arange(100) * 1e-4
U_RP = np.zeros((100, 2))


def test_run_plant_shapes():
    with _raises("`t`"):
        pj.run_plant(DRIVE, T_RP[:1], U_RP[:1])
    with _raises("`u_ab`"):
        pj.run_plant(DRIVE, T_RP, U_RP[:, :1])
    with _raises("`u_ab`"):
        pj.run_plant(DRIVE, T_RP, U_RP[:99])


def _t_non_uniform():
    t = T_RP.copy()
    t[50] += 3e-5
    return t


@pytest.mark.parametrize("case", ["non_uniform", "decreasing", "nan"])
def test_run_plant_time_axis(case):
    t = {"non_uniform": _t_non_uniform(), "decreasing": T_RP[::-1],
         "nan": np.where(np.arange(100) == 3, np.nan, T_RP)}[case]
    with _raises("`t`"):
        pj.run_plant(DRIVE, t, U_RP)


def test_run_plant_T_s_too_long():
    with _raises("`T_s=0.005` s is too long"):
        pj.run_plant(DRIVE, T_RP * 50, U_RP, n_substeps=1)
