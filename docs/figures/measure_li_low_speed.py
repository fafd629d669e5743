"""Why the li observers lose their low-speed validation runs (docs/tuning.md): for each of
the C-, GI- and FA-LESO with its paper design on `li_dtp`, the tuner's validation set
(`python -m tuning --observer NAME` with its defaults) is run twice, sensorless and with
the sensored observer (the same controller on the rotor's true angle and speed), and for
every run that loses lock sensorless it prints: the sensored run's lowest speed (p.u.),
whether the rotor reverses in either run, and at the sensored run's lowest speed the
back-EMF |w| psi_f against the voltage a 30 % resistance error leaves in the observer's
model at the sensored run's current (V). About two minutes per observer on two cores.

    .venv/bin/python docs/figures/measure_li_low_speed.py [c-leso gi-leso fa-leso]
"""

import sys

import jax
import numpy as np

import pmsmjax as pj
from tuning.problem import TuningProblem
from tuning.scenarios import simulate_set, validation_set


def measure(name: str) -> None:
    problem = TuningProblem(observer=name, motor="li_dtp")
    drive = problem.drive()
    foc = pj.FOC.from_drive(drive)
    sset = validation_set(problem)
    kw = dict(T_s=problem.T_s, noise_std=problem.noise_std, save_every=1)
    own = simulate_set(lambda m: pj.observers.make_observer(name, drive, motor=m), drive,
                       foc, sset, **kw)
    ref = simulate_set(lambda m: pj.SensoredObserver(), drive, foc, sset, **kw)
    lost = np.asarray(pj.lock_status(own.t, own.theta_err,
                                     ok=np.asarray(own.status._value) == 0)["lost"])
    s1 = np.asarray(sset.s1)
    w_r, psi_f, R_s = float(drive.w_rated), float(drive.motor.psi_f), float(drive.motor.R_s)
    w_ref, w_own = np.asarray(ref.w_m), np.asarray(own.w_m)
    reverses = lambda w, j: bool(np.any(np.sign(w[j]) != np.sign(s1[j])))  # noqa: E731
    print(f"{name}: {int(lost.sum())} of {lost.size} validation runs lose lock; the "
          f"sensored runs reverse in {sum(reverses(w_ref, j) for j in range(s1.size))}")
    for j in np.nonzero(lost)[0]:
        k = int(np.argmin(np.abs(w_ref[j])))
        i = float(np.linalg.norm(np.asarray(ref.i_dq)[j, k]))
        k_R = float(sset.k_R[j])
        print(f"  {s1[j]:+.2f} p.u., (k_d, k_q, k_R, k_psi) = "
              f"({float(sset.k_d[j]):.2f}, {float(sset.k_q[j]):.2f}, {k_R:.2f}, "
              f"{float(sset.k_psi[j]):.2f}): sensored lowest speed "
              f"{abs(w_ref[j, k]) / w_r:.3f} p.u. at {float(ref.t[j, k]):.3f} s, reverses "
              f"sensored {reverses(w_ref, j)}, sensorless {reverses(w_own, j)}; there "
              f"back-EMF {abs(w_ref[j, k]) * psi_f:.2f} V, 0.3 R_s |i| = "
              f"{0.3 * R_s * i:.2f} V (|i| {i:.2f} A)", flush=True)


if __name__ == "__main__":
    pj.runtime.configure()
    jax.config.update("jax_enable_x64", True)
    for name in sys.argv[1:] or ["c-leso", "gi-leso", "fa-leso"]:
        measure(name)
