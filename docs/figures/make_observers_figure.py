"""Regenerate `docs/figures/observers.png`, the first figure of the observers page: an
observer in the closed loop and the analysis that predicts it, with the public API only.

(a) The README's drive: zhang2022's ESO on zhang750 whose model of L_q is 30 % high, at
0.5 p.u. speed, half the rated torque applied at 0.2 s: the angle error against time,
and the stable equilibrium that `analysis.equilibria` gives for the current drawn.
(b) The same mismatch for several registered observers (each with its paper's design on
zhang750): the stable designed equilibrium's angle against the load current (in the
estimated frame), from `analysis.equilibria` under `jax.vmap`. A few minutes on 2 cores.

    .venv/bin/python docs/figures/make_observers_figure.py
"""

import pathlib

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

import pmsmjax as pj
from pmsmjax import analysis


matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


HERE = pathlib.Path(__file__).resolve().parent
OBSERVERS = ("eso", "leso", "afo", "parallel-model", "rotor-flux", "fa-leso")


def designed_angle(eq) -> np.ndarray:
    """Per point: the angle (deg) of the stable equilibrium nearest zero (NaN if none)."""
    theta = np.degrees(np.asarray(eq.theta))
    ok = np.asarray(eq.valid) & np.asarray(eq.stable)
    theta = np.where(ok, theta, np.nan)
    pick = np.nanargmin(np.where(ok, np.abs(theta), np.inf), axis=-1)
    out = np.take_along_axis(theta, pick[..., None], axis=-1)[..., 0]
    return np.where(ok.any(axis=-1), out, np.nan)


if __name__ == "__main__":
    pj.runtime.configure()
    drive = pj.preset("zhang750")
    plant = drive.three_phase_motor
    wrong = pj.replace_params(drive, L_q=1.3 * plant.L_q).three_phase_motor
    w = 0.5 * drive.w_rated

    # (a) the closed loop
    eso = pj.observers.make_observer("eso", drive, motor=wrong)
    scenario = pj.Scenario(t_end=0.6, w_m_ref=pj.Profile.constant(w),
                           tau_L=pj.Profile.steps([0.2], [0.5 * drive.tau_rated]))
    traj = pj.simulate(drive, pj.FOC.from_drive(drive), eso, scenario, T_s=125e-6, w_m0=w)
    t, err = np.asarray(traj.t), np.degrees(np.asarray(traj.theta_err))
    i_abs = float(np.hypot(*np.asarray(traj.i_dq)[-1]))
    eq = analysis.equilibria(eso, plant, float(traj.w_m[-1]), (0.0, i_abs))
    theta_eq = float(designed_angle(eq))

    # (b) the analysis over the load current, every observer
    i_q = jnp.linspace(0.0, 1.0, 11) * float(drive.i_max)
    curves = {}
    for name in OBSERVERS:
        obs = pj.observers.make_observer(name, drive, motor=wrong)
        eqs = jax.vmap(lambda i: analysis.equilibria(obs, plant, w, jnp.stack(
            [jnp.zeros_like(i), i])))(i_q)
        curves[name] = designed_angle(eqs)
        print(name, np.round(curves[name], 2))

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.6))
    ax1.plot(t, err, lw=1, label="simulated (closed loop)")
    ax1.axhline(theta_eq, color="k", ls="--", lw=0.8,
                label=f"analysis.equilibria: {theta_eq:.2f} deg")
    ax1.axvline(0.2, color="0.6", ls=":", lw=0.8)
    ax1.set_xlabel("time (s)")
    ax1.set_ylabel("angle error (deg)")
    ax1.set_title("(a) ESO with L_q 30 % high: load step at 0.2 s", fontsize=10)
    ax1.legend(fontsize=8, loc="center right")
    i_pu = np.asarray(i_q) / float(drive.i_max)
    for name, c in curves.items():
        ax2.plot(i_pu, c, "o-", ms=3, label=name)
    ax2.set_xlabel("load current i_q (fraction of the current limit)")
    ax2.set_ylabel("designed equilibrium (deg)")
    ax2.set_title("(b) every observer, same mismatch, 0.5 p.u. speed", fontsize=10)
    ax2.legend(fontsize=8, ncol=2)
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(HERE / "observers.png", dpi=110)
    print(f"wrote {HERE / 'observers.png'}")
