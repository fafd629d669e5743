"""Why the li observers lose their low-speed validation runs (docs/tuning.md): for each of
the C-, GI- and FA-LESO with its paper design on `li_dtp`, the tuner's validation set
(`python -m tuning --observer NAME` with its defaults) is run sensorless, and every run
that loses lock is run again with the sensored observer (the same controller on the
rotor's true angle and speed: `tuning.scenarios.sensored_lowest_speed`). Printed per
lost run: the sensored run's lowest speed (p.u.), whether the rotor reverses in either
run, and at that lowest speed the back-EMF |w| psi_f against the voltage a 30 %
resistance error leaves in the observer's model at the current there (V). About two
minutes per observer on two cores.

    .venv/bin/python docs/figures/measure_li_low_speed.py [c-leso gi-leso fa-leso]
"""

import sys

import jax
import numpy as np

import pmsmjax as pj
from tuning.problem import TuningProblem
from tuning.scenarios import sensored_lowest_speed, simulate_set, validation_set


def measure(name: str) -> None:
    problem = TuningProblem(observer=name, motor="li_dtp")
    drive = problem.drive()
    sset = validation_set(problem)
    own = simulate_set(lambda m: pj.observers.make_observer(name, drive, motor=m), drive,
                       problem.controller(), sset, T_s=problem.T_s,
                       noise_std=problem.noise_std, save_every=1)
    lost = np.asarray(pj.lock_status(own.t, own.theta_err, start_locked=True,
                                     ok=np.asarray(own.status._value) == 0)["lost"])
    s1, w_own = np.asarray(sset.s1), np.asarray(own.w_m)
    R_s = float(drive.motor.R_s)
    print(f"{name}: {int(lost.sum())} of {lost.size} validation runs lose lock")
    for r in sensored_lowest_speed(problem, sset, np.nonzero(lost)[0]):
        j = r["run"]
        print(f"  {s1[j]:+.2f} p.u., (k_d, k_q, k_R, k_psi) = "
              f"({float(sset.k_d[j]):.2f}, {float(sset.k_q[j]):.2f}, "
              f"{float(sset.k_R[j]):.2f}, {float(sset.k_psi[j]):.2f}): sensored lowest "
              f"speed {r['lowest_speed_pu']:.3f} p.u. at {r['t_s']:.3f} s, reverses "
              f"sensored {r['reverses']}, sensorless "
              f"{bool(np.any(np.sign(w_own[j]) == -np.sign(s1[j])))}; there back-EMF "
              f"{r['back_emf_V']:.2f} V, 0.3 R_s |i| = {0.3 * R_s * r['current_A']:.2f} V "
              f"(|i| {r['current_A']:.2f} A)", flush=True)


if __name__ == "__main__":
    pj.runtime.configure()
    jax.config.update("jax_enable_x64", True)
    for name in sys.argv[1:] or ["c-leso", "gi-leso", "fa-leso"]:
        measure(name)
