"""Why the rotor-flux observer's sensorless loop loses lock on the saturated preset
(docs/saturation.md): its speed estimate answers the q current once the model is off.

ipm3k5_sat at 0.5 p.u. speed, the observer with its constant (small-current) model:

1. the transfer from the q current to the speed estimate's error, G(f) = d(w_hat - w) /
   d i_q, measured in open loop: a sensored drive at an imposed speed with a 2 % q-current
   sinusoid on a steady q current, the observer replayed over the recording (on the
   constant machine, morawiec_ipm3k5, it is zero to round-off);
2. the speed PI's proportional gain k_p (A per rad/s of electrical speed) closes the loop
   w_hat -> i_q -> w_hat: where k_p |G| passes 1 with G's phase near 180 deg, it is
   unstable;
3. the closed loop with a slow load ramp (0 -> 0.3 of rated torque from 0.2 s to 0.7 s)
   at the default 5 Hz speed loop: the observer's speed estimate in the controller, the
   same with the true speed given to the controller (a diagnostic, not a drive), and the
   constant machine.

Run from the repository root: `python docs/figures/make_rotor_flux_speed_loop.py`
(writes docs/figures/rotor_flux_speed_loop.png and rotor_flux_speed_loop.json)."""

import dataclasses
import json
import math
import os

import jax
import matplotlib
import numpy as np


matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402

import pmsmjax as pj  # noqa: E402
from pmsmjax.observers import make_observer  # noqa: E402


jax.config.update("jax_enable_x64", True)
HERE = os.path.dirname(os.path.abspath(__file__))
FREQS = (10.0, 20.0, 30.0, 40.0, 45.0, 50.0, 55.0, 60.0, 65.0, 70.0, 80.0, 100.0, 150.0)
LOADS = (0.1, 0.3)  # q current, p.u. of the current limit
BANDWIDTHS = (2.0, 5.0)  # speed loop, Hz


def transfer(drive, i_q_pu, f, speed_pu=0.5, amplitude_pu=0.02, t_end=0.6, t_on=0.2):
    """G(f) (rad/s per A): the speed estimate's error over the q current at `f` (Hz)."""
    w = speed_pu * float(drive.w_rated)
    i_max = float(drive.i_max)
    ts = np.arange(0.0, t_end, 1e-4)
    i_q = i_q_pu * i_max + amplitude_pu * i_max * np.sin(2 * np.pi * f * ts) * (ts > t_on)
    sc = pj.Scenario(t_end=t_end, w_m_imposed=pj.Profile.constant(w),
                     i_d_ref=pj.Profile.constant(0.0), i_q_ref=pj.Profile(list(ts), list(i_q)))
    tr = pj.simulate(drive, pj.FOC.from_drive(drive), pj.SensoredObserver(), sc, w_m0=w)
    _, w_hat = pj.replay(make_observer("rotor-flux", drive),
                         pj.RecordedData.from_trajectory(tr), theta0=tr.theta[0], w0=w)
    t = np.asarray(tr.t)
    m = t > t_on + 0.2
    z = np.exp(-2j * np.pi * f * t[m])
    dw = (np.asarray(w_hat) - np.asarray(tr.w_m))[m]
    return complex(np.mean(dw * z) / np.mean(np.asarray(tr.i_dq)[m, 1] * z))


class _TrueSpeed:
    """The observer's angle with the rotor's true speed (a diagnostic: which estimate
    breaks the loop)."""

    @staticmethod
    def wrap(observer):
        cls = type(observer)

        class TrueSpeed(cls):
            def step(self, state, meas, T_s):
                state, est = super().step(state, meas, T_s)
                return state, dataclasses.replace(est, w_hat=meas.w_m)

        return TrueSpeed(**{f.name: getattr(observer, f.name)
                            for f in dataclasses.fields(observer)})


def closed_loop(drive, observer, load_pu=0.3, speed_pu=0.5):
    w = speed_pu * float(drive.w_rated)
    sc = pj.Scenario(t_end=1.5, w_m_ref=pj.Profile.constant(w),
                     tau_L=pj.Profile.ramp(0.2, 0.7, 0.0, load_pu * float(drive.tau_rated)))
    return pj.simulate(drive, pj.FOC.from_drive(drive), observer, sc, w_m0=w, throw=False)


if __name__ == "__main__":
    sat, const = pj.preset("ipm3k5_sat"), pj.preset("morawiec_ipm3k5")
    i_max = float(sat.i_max)
    G = {load: [transfer(sat, load, f) for f in FREQS] for load in LOADS}
    G_const = max(abs(transfer(const, load, 55.0)) for load in LOADS)
    ctrl = pj.FOC.from_drive(sat)
    k_tau = 1.5 * float(sat.motor.n_p) * float(sat.motor.psi_f)
    k_p = {bw: 2 * (2 * math.pi * bw) * float(ctrl.speed.J_over_np) / k_tau for bw in BANDWIDTHS}
    obs = make_observer("rotor-flux", sat)
    runs = {"map, the observer's speed estimate": closed_loop(sat, obs),
            "map, the true speed to the controller": closed_loop(sat, _TrueSpeed.wrap(obs)),
            "constant machine": closed_loop(const, make_observer("rotor-flux", const))}

    fig, (ax_g, ax_w) = plt.subplots(2, 1, figsize=(7.5, 6.0))
    for load, colour in zip(LOADS, ("C0", "C3")):
        ax_g.plot(FREQS, [abs(g) for g in G[load]], "o-", color=colour,
                  label=f"|G|, map, i_q = {load:g} i_max ({load * i_max:.2f} A)")
    for bw, ls in zip(BANDWIDTHS, ("--", ":")):
        ax_g.axhline(1 / k_p[bw], color="k", ls=ls, lw=0.8,
                     label=f"1 / k_p of a {bw:g} Hz speed loop")
    ax_g.set_yscale("log")
    ax_g.set_xlabel("frequency of the q current (Hz)")
    ax_g.set_ylabel("|d(w_hat - w) / d i_q| (rad/s per A)")
    ax_g.legend(fontsize=7)
    for (label, tr), colour in zip(runs.items(), ("C3", "C0", "0.4")):
        t = np.asarray(tr.t)
        ax_w.plot(t, np.degrees(np.asarray(tr.theta_err)), color=colour, lw=0.7,
                  label=label)
    ax_w.set_ylim(-185, 185)
    ax_w.set_xlabel("t (s); load ramped 0 -> 0.3 of rated torque from 0.2 s to 0.7 s")
    ax_w.set_ylabel("angle error (deg), 5 Hz speed loop")
    ax_w.legend(fontsize=7, loc="lower left")
    fig.suptitle("ipm3k5_sat, rotor-flux observer, 0.5 p.u.: the speed estimate closes the "
                 "loop", fontsize=9)
    fig.tight_layout()
    fig.savefig(os.path.join(HERE, "rotor_flux_speed_loop.png"), dpi=110)

    summary = {
        "frequencies_Hz": list(FREQS),
        "G_abs_rad_s_per_A": {str(k): [abs(g) for g in v] for k, v in G.items()},
        "G_phase_deg": {str(k): [math.degrees(np.angle(g)) for g in v] for k, v in G.items()},
        "G_abs_constant_machine_max": G_const,
        "k_p_A_per_rad_s": {str(k): v for k, v in k_p.items()},
        "closed_loop_last_0.3s": {
            label: {"theta_err_mean_deg": float(np.degrees(np.mean(
                        np.asarray(tr.theta_err)[np.asarray(tr.t) > 1.2]))),
                    "w_hat_err_rms_rad_s": float(np.sqrt(np.mean(np.asarray(
                        tr.w_hat - tr.w_m)[np.asarray(tr.t) > 1.2] ** 2)))}
            for label, tr in runs.items()},
    }
    with open(os.path.join(HERE, "rotor_flux_speed_loop.json"), "w") as f:
        json.dump(summary, f, indent=1)
    print(json.dumps(summary, indent=1))
