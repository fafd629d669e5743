r"""The experiments of zhang2022 (Sec. VI, Figs. 2-11) as named, reproducible simulations.

M. Zhang, B. Xia, J. Zhang, "Parameter Design and Convergence Analysis of Flux Observer for
Sensorless PMSM Drives", IEEE Trans. Energy Convers. 37(4), 2022.

`experiment(name, drive)` builds one experiment: the scenario, every argument of
`simulate`, the observers to replay over the simulated record (for the paper's
"sensing mode" figures) and the paper's published numbers. `Experiment.run()`
simulates it and returns the estimates and error statistics (measured with
`pmsmjax.replay_stats`, `settling_time` and `error_stats`). The tests and the notebook
`02_eso_observers.ipynb` share these definitions; `EXPERIMENTS` lists the names.

Common settings (Sec. VI-A; everything the paper does not state is an assumption and is
named here):

- machine: `preset("zhang750")` (Table I; inertia assumed, see `Drive.notes`);
- sampling 8 kHz (`T_s = 125e-6` s), FOC with current bandwidth 2 pi 500 rad/s and speed
  bandwidth 2 pi 5 rad/s, `i_d = 0`, no computational delay;
- speeds "in p.u." are fractions of `drive.w_rated`, loads of `drive.tau_rated`;
- observer: `ESOObserver` with the design zhang2022 (38), (25), `w2 = 2 pi 50` rad/s
  (Figs. 2-6, 9-11) or as the figure says (250/150 Hz in Figs. 7-8), `zeta2 = 1`, fal
  `a = 0.5`, `eta = 0.05 psi_f` (the paper gives neither);
- current-sensor noise: white, `noise_std = 0.02` A per component (assumed: about two
  LSB of a 12-bit converter over +-20 A; the paper reports no noise level). No dead time
  or other inverter non-linearity is modelled (the paper compensates them [37]), so the
  low-speed offsets the paper attributes to them are absent here.

Closed-loop ("sensorless mode") figures 2-6 and 9 run the observer in the loop. The
"sensing mode" figures 7, 8, 10, 11 control the drive with the encoder
(`SensoredObserver`) and run the compared observers open loop over the recorded
voltages and currents from `replay_from` on, from zero initial conditions
($\hat\theta = 0$, $\hat\omega = 0$), as the paper describes.
"""

from __future__ import annotations

import dataclasses
import math

import jax.random as jr
import numpy as np

from .._control._foc import FOC
from .._data._replay import replay
from .._frames import park
from .._plant._params import Drive, scale_motor
from .._plant._presets import preset
from .._sim._metrics import error_stats, replay_stats, settling_time
from .._sim._scenario import Profile, Scenario
from .._sim._simulate import Sensing, simulate
from ..analysis import equilibria
from ..observers import (
    AFOObserver,
    ESODesign,
    ESOObserver,
    FixedGains,
    LESOObserver,
    SensoredObserver,
)


EXPERIMENTS = ("fig2", "fig3", "fig4", "fig5", "fig6", "fig7", "fig8", "fig9", "fig10",
               "fig11")

#: Numbers printed in zhang2022 Sec. VI (angles in deg, times in s, bands in %).
PUBLISHED = {
    "fig2": {"t_converge_s": 0.35, "theta_err_mean_deg": 0.11, "theta_err_std_deg": 0.69,
             "theta_err0_deg": 30.0, "w_band_pct": 5.0},
    "fig3": {"theta_err_mean_deg": 1.45, "theta_err_std_deg": 0.10, "w_band_pct": 15.0},
    "fig4": {"theta_err_mean_deg": 0.07, "theta_err_std_deg": 0.08, "w_band_pct": 1.0},
    "fig5": {"note": "speed estimate tracks the real speed closely and smoothly"},
    "fig6": {"note": "speed dips and recovers; the estimate follows the load steps"},
    "fig7": {"note": "equal speed of response at 250 Hz; ESO speed estimate fluctuates "
                     "less than the AFO's"},
    "fig8": {"note": "AFO at 150 Hz has about the ESO's (250 Hz) fluctuation; the ESO "
                     "responds faster with smaller overshoot"},
    "fig9": {"theta_err_static_deg": 23.18, "theta_err_theory_deg": 20.91,
             "theta_err0_deg": -14.53},
    "fig10": {"note": "ESO with L/2 deteriorated but acceptable; AFO with L/2 responds "
                      "slower"},
    "fig11": {"note": "0.2 p.u.: both converge; 0.4: fixed gains slower; 0.6: adaptive "
                      "converges, fixed gains do not converge"},
}


@dataclasses.dataclass(frozen=True)
class ExperimentResult:
    """Output of `Experiment.run()`.

    - `traj`: the `Trajectory` of the simulated drive.
    - `t`: time axis of the estimates (s); for replays it starts at 0 at `replay_from`.
    - `theta`, `w_m`: true angle (rad) and speed (rad/s) on `t`.
    - `estimates`: `{observer name: (theta_hat, w_hat)}` on `t`.
    - `stats`: `{observer name: dict}` from `replay_stats` plus experiment metrics.
    - `theory`: extra computed references (Fig. 9: `i_dq0`, the mean current in the
      estimated frame (A); `w0`, the speed (rad/s); `equilibria`, the `Equilibria` there
      of the error dynamics zhang2022 (11) with linear feedback, which the paper's
      analysis zhang2022 (34)-(36) assumes).
    """

    traj: object
    t: np.ndarray
    theta: np.ndarray
    w_m: np.ndarray
    estimates: dict
    stats: dict
    theory: dict


@dataclasses.dataclass(frozen=True)
class Experiment:
    """One experiment of zhang2022 Sec. VI (see the module docstring).

    - `name`, `title`: e.g. `"fig2"`, and a one-line description.
    - `drive`: the plant's `Drive`.
    - `scenario`: the `Scenario`.
    - `kwargs`: every argument of `simulate` except the drive:
      `simulate(exp.drive, **exp.kwargs)` runs it (this holds `scenario`, `controller`,
      `observer`, `T_s`, `sensing`, `key` and initial conditions).
    - `observers`: `{name: observer}` replayed over the record (sensing-mode figures);
      empty for closed-loop figures, whose in-loop observer is `kwargs["observer"]`.
    - `replay_from`: start of the replays (s).
    - `t_settle`: statistics use times >= `t_settle` on the estimates' time axis (s).
    - `w_op`: operating speed for relative speed metrics (rad/s).
    - `published`: the paper's numbers (`PUBLISHED[name]`).
    """

    name: str
    title: str
    drive: Drive
    scenario: Scenario
    kwargs: dict
    observers: dict
    replay_from: float
    t_settle: float
    w_op: float
    published: dict

    @property
    def closed_loop(self) -> bool:
        return not self.observers

    def simulate(self):
        """`simulate(drive, **kwargs)`: the drive's `Trajectory`."""
        return simulate(self.drive, **self.kwargs)

    def run(self) -> ExperimentResult:
        """Simulate, replay the open-loop observers, and compute statistics."""
        traj = self.simulate()
        theory = {}
        if self.closed_loop:
            t = np.asarray(traj.t)
            estimates = {"eso": (np.asarray(traj.theta_hat), np.asarray(traj.w_hat))}
            theta, w_m = np.asarray(traj.theta), np.asarray(traj.w_m)
        else:
            k0 = int(round(self.replay_from / self.kwargs["T_s"]))
            t_all = np.asarray(traj.t)
            t = t_all[k0:] - t_all[k0]
            theta, w_m = np.asarray(traj.theta)[k0:], np.asarray(traj.w_m)[k0:]
            estimates = {}
            for name, obs in self.observers.items():
                # the paper's observers start from zero (its Figs. 7-11 show them
                # converging from there), not from `replay`'s default unknown start
                th, w = replay(obs, t, traj.u_ab[k0:], traj.i_meas_ab[k0:],
                               T_s=self.kwargs["T_s"], theta0=0.0, w0=0.0)
                estimates[name] = (np.asarray(th), np.asarray(w))
        stats = {}
        w_abs = abs(self.w_op)
        for name, (th, w) in estimates.items():
            s = replay_stats(t, th, w, theta, w_m, t_settle=self.t_settle)
            w_err = w_m - w
            s["t_w_converge_s"] = float(settling_time(t, w_err, 0.05 * w_abs))
            s["w_hat_overshoot_pct"] = float(100 * (np.max(w) - np.max(w_m)) / w_abs)
            stats[name] = s
        if self.closed_loop:
            s = stats["eso"]
            mask = t >= self.t_settle
            w_track_err = np.asarray(traj.w_m_ref) - w_m
            s["w_track_err_max_pct"] = 100 * error_stats(w_track_err[mask])["max_abs"] / w_abs
            s["theta_err_max_all_deg"] = error_stats(
                np.degrees(np.asarray(traj.theta_err)))["max_abs"]
            s["w_dip_max_pct"] = 100 * error_stats(w_track_err)["max_abs"] / w_abs
            if self.name == "fig9":
                i_c = np.asarray(park(traj.i_meas_ab, traj.theta_hat))[mask].mean(0)
                obs = self.kwargs["observer"]
                if isinstance(obs, ESOObserver):  # the paper analyses linear feedback
                    obs = LESOObserver(obs.motor, obs.design)
                theory = {"i_dq0": i_c, "w0": self.w_op,
                          "equilibria": equilibria(obs, self.drive.three_phase_motor,
                                                   self.w_op, i_c)}
        return ExperimentResult(traj=traj, t=t, theta=theta, w_m=w_m, estimates=estimates,
                                stats=stats, theory=theory)


def experiment(name: str, drive: Drive | None = None, *, T_s: float = 125e-6,
               noise_std: float = 0.02, seed: int = 0, w_pu: float | None = None,
               load_pu: float = 0.0, bandwidth_hz: float = 50.0,
               observer=None) -> Experiment:
    """One experiment of zhang2022 Sec. VI by name.

    **Arguments:**

    - `name`: `"fig2"` ... `"fig11"` (`EXPERIMENTS`).
    - `drive`: the plant (default `preset("zhang750")`).
    - `T_s`: sampling period (s), default 125e-6 (8 kHz, as the paper).
    - `noise_std`: current-sensor noise (A per component); 0 = none.
    - `seed`: PRNG seed of the noise.
    - `w_pu`: operating speed (p.u.) for `"fig11"` (0.2, 0.4 or 0.6 in the paper;
      default 0.2).
    - `load_pu`: load torque (p.u.) for `"fig10"`; the paper states none (default 0). At
      zero load the current, and so the inductance error, hardly enters the observer.
    - `bandwidth_hz`: observer bandwidth w2 / (2 pi) (Hz) of the figures that use the
      paper's 50 Hz (all but Figs. 7-8).
    - `observer`: replaces the in-loop observer of the closed-loop figures (e.g. an
      `LESOObserver` or `AFOObserver` to exercise them the same way).

    **Returns:** an `Experiment`; `exp.run()` simulates it.
    """
    if name not in EXPERIMENTS:
        raise ValueError(
            f"Unknown experiment {name!r}; choose one of {', '.join(EXPERIMENTS)}."
        )
    drive = preset("zhang750") if drive is None else drive
    wr = float(drive.w_rated)
    tr = float(drive.tau_rated)
    m = drive.three_phase_motor
    foc = FOC.from_drive(drive)
    sensing = Sensing(noise_std=noise_std)
    key = jr.PRNGKey(seed) if noise_std > 0 else None
    bw = 2 * math.pi * float(bandwidth_hz)
    eso = ESOObserver.from_drive(drive, w2=bw) if observer is None else observer
    common = dict(controller=foc, T_s=T_s, sensing=sensing, key=key)

    def closed(title, scenario, w_op, t_settle, obs=eso, **init):
        kw = dict(common, observer=obs, scenario=scenario, **init)
        return Experiment(name, title, drive, scenario, kw, {}, 0.0, t_settle, w_op,
                               PUBLISHED[name])

    def sensing_mode(title, w_op, t_end, observers, replay_from=0.1, t_settle=None,
                     load=0.0):
        sc = Scenario(t_end=t_end, w_m_ref=Profile.constant(w_op),
                      tau_L=Profile.constant(load) if load else None)
        kw = dict(common, observer=SensoredObserver(), scenario=sc, w_m0=w_op)
        t_settle = 0.5 * (t_end - replay_from) if t_settle is None else t_settle
        return Experiment(name, title, drive, sc, kw, observers, replay_from,
                               t_settle, w_op, PUBLISHED[name])

    if name == "fig2":
        w_op = 0.05 * wr
        sc = Scenario(t_end=1.0, w_m_ref=Profile.ramp(0.0, 0.2, 0.0, w_op),
                      tau_L=Profile.constant(0.1 * tr))
        return closed("Loaded ramp to 0.05 p.u. (0.1 p.u. load), 30 deg initial error",
                      sc, w_op, 0.6, theta0=0.0, theta_hat0=-math.radians(30.0))
    if name in ("fig3", "fig4"):
        pu, load, t_end = (0.01, 0.01, 1.5) if name == "fig3" else (1.0, 1.0, 0.8)
        w_op = pu * wr
        sc = Scenario(t_end=t_end, w_m_ref=Profile.constant(w_op),
                      tau_L=Profile.constant(load * tr))
        return closed(f"Steady state at {pu} p.u. with {load} p.u. load", sc, w_op,
                      t_end - 0.4, w_m0=w_op)
    if name == "fig5":
        sc = Scenario(t_end=1.0, w_m_ref=Profile.steps([0.05, 0.6], [wr, 0.5 * wr]))
        return closed("Speed steps 0 -> 1 -> 0.5 p.u., no load", sc, wr, 0.9)
    if name == "fig6":
        w_op = wr
        sc = Scenario(t_end=3.0, w_m_ref=Profile.constant(w_op),
                      tau_L=Profile.steps([0.5, 2.25], [0.25 * tr, -0.25 * tr]))
        return closed("Load steps +0.25 / -0.25 p.u. at 1.0 p.u.", sc, w_op, 2.9,
                      w_m0=w_op)
    if name in ("fig7", "fig8"):
        w_afo = 2 * math.pi * (250.0 if name == "fig7" else 150.0)
        obs = {"eso": ESOObserver.from_drive(drive, w2=2 * math.pi * 250.0),
               "afo": AFOObserver.from_drive(drive, w2=w_afo)}
        title = ("Noise at equal bandwidth: ESO 250 Hz vs AFO 250 Hz, sensing mode, "
                 "0.25 p.u." if name == "fig7" else
                 "Speed of response: ESO 250 Hz vs AFO 150 Hz, sensing mode, 0.25 p.u.")
        return sensing_mode(title, 0.25 * wr, 0.4, obs, t_settle=0.15)
    if name == "fig9":
        w_op = 0.5 * wr
        design = ESODesign.fixed_ratio(0.5, 0.5, bw)
        obs = ESOObserver(m, design) if observer is None else observer
        sc = Scenario(t_end=1.0, w_m_ref=Profile.ramp(0.0, 0.3, 0.0, w_op))
        return closed("Infeasible design zeta1 = 0.5, w1 = 0.5 w0: ramp to 0.5 p.u., "
                      "-14.53 deg initial error", sc, w_op, 0.7, obs=obs, theta0=0.0,
                      theta_hat0=math.radians(14.53))
    if name == "fig10":
        half = scale_motor(m, {"L_d": 0.5, "L_q": 0.5})
        obs = {"eso": ESOObserver.from_drive(drive, w2=bw),
               "eso_half_L": ESOObserver.from_drive(drive, w2=bw, motor=half),
               "afo": AFOObserver.from_drive(drive, w2=bw),
               "afo_half_L": AFOObserver.from_drive(drive, w2=bw, motor=half)}
        return sensing_mode("Inductance at half its nominal value, sensing mode, 0.1 p.u., "
                            f"load {load_pu:g} p.u.", 0.1 * wr, 0.6, obs, t_settle=0.3,
                            load=load_pu * tr)
    # fig11
    pu = 0.2 if w_pu is None else float(w_pu)
    design = ESODesign.zhang38(wr, bw)
    obs = {"adaptive": ESOObserver(m, design),
           "fixed": ESOObserver(m, FixedGains.at(design, m, 0.2 * wr))}
    return sensing_mode(f"Adaptive (scheduled) vs fixed gains (frozen at 0.2 p.u.) at {pu} "
                        "p.u., sensing mode", pu * wr, 0.8, obs, t_settle=0.4)

