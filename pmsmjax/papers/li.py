r"""The experiments of li-fa-leso (Sec. V, Figs. 10-18) as named simulations, with the
published numbers next to them.

Y. Li, Y. Hu, X. Ma, L. Liu, "Sensorless Control of Dual Three-Phase IPMSM Based on
Frequency Adaptive Linear Extended State Observer".

Common settings (everything the paper does not state is an assumption):

- machine: `preset("li_dtp")` (assumed: the paper gives no machine table, see
  `Drive.notes`); back-EMF 5th 3 %, 7th 2 % (assumed amplitudes);
- sampling `T_s = 100 us`, FOC current bandwidth 2 pi 500 rad/s, `i_d = 0`;
- observers: `make_observer(name, drive)`, Table II (C-LESO $\omega_0 = 500\pi$, GI-LESO
  $\omega_0 = 500\pi$, $K_r = 2\omega_0^2$, $\omega_c = \pi$ with its resonance on the
  PLL's speed, FA-LESO $k_1 = 10\pi$, $k_2 = 100\pi$), PLL 20 Hz critically damped;
- steady-state tests (Figs. 10-15, 18) run at a speed imposed by a load machine with
  current control ("load in p.u." = $i_q$ in p.u. of the rated current; the paper's
  field weakening at 840 rpm is not modelled: $i_d = 0$ throughout); transients
  (Figs. 16-17) run the speed loop on the observer's estimates;
- "individual sets" (Figs. 13-14): as the paper does, the DTP machine is treated as two
  single three-phase PMSMs and the observer sees set 1: simulated as the three-phase
  machine with li_dtp's per-set parameters, whose 5th and 7th back-EMF harmonics are in
  its alpha-beta plane (`individual_set_drive`). VSD control (Fig. 15): the dual machine,
  whose 5th and 7th harmonics the plant maps to the x-y subspace (see `pmsmjax.PMSM`), so
  the alpha-beta observer does not see them; the x-y currents are regulated to zero
  (`FOC.from_drive(drive, dual="vsd")`: PI in the anti-synchronous frame plus integrators
  at the 5th and 7th, see `pmsmjax.DualCurrentControl`), which keeps the 5th and 7th out
  of the phase currents too.

**Mismatch (Fig. 18, (39)-(43)).** In steady state the observer's model signal is
$\hat L_q\rho = \omega J(L i + \psi_f e_d) + (R_s - \hat R_s)i - \omega\hat L_qJi$ (true
rotor frame, true current $i = e^{-\tilde\theta J}\hat i$), the estimate is
$\hat e = G(j\omega)\hat L_q\rho$ and the PLL locks where its d component in the
estimated frame vanishes. With $\Sigma = (L_d + L_q)/2$, $\Delta = (L_q - L_d)/2$,
$\delta R = R_s - \hat R_s$ and $G = 1$ (FA-LESO) this is the scalar equation

$$-\omega\psi_f\sin\tilde\theta - \omega(\Sigma + \Delta\cos2\tilde\theta - \hat L_q)\hat
i_q + \omega\Delta\sin2\tilde\theta\,\hat i_d + \delta R\,\hat i_d = 0$$

(`mismatch_offset`, any $G$, solved by Newton), exact for any current. The printed
(42)-(43), $\arctan(-\Delta R\hat i_d/(E_{ex} - \Delta R\hat i_q))$ and
$\arctan(\Delta L_q\hat i_q/(E_{ex}/\hat\omega - \Delta L_q\hat i_d))$, evaluate the
mismatch voltage with the estimated-frame currents as if they were the true ones and use
$\arctan$ of the ratio where the angle enters through $\sin$; they match the exact root
only to first order, and for them to have the right sign $\Delta X$ must be read as
model minus true ($\hat X - X$, the opposite of (33)'s definition). For $R_s$ the
printed form is exact at $\hat i_d = 0$ (both give 0); for $L_q$ it is not exact even
then (its error grows with $\hat i_q$ and $\Delta L_q$) — `mismatch_table` gives the
numbers. `pmsmjax.analysis.equilibria` of the observer with the mismatched model finds
the same angle (tested).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import pmsmjax as pj
from pmsmjax.observers import OperatingPoint, make_observer


NAMES = ("c-leso", "gi-leso", "fa-leso")
T_S = 1e-4

#: Published numbers (deg, %, rpm) read from the text of Sec. V.
PUBLISHED = {
    # Figs. 10-12: mean position error at no load (deg)
    "position_error_deg": {"c-leso": {300: 14.0, 600: 23.0, 840: 34.0},
                           "gi-leso": {300: 7.0, 600: 10.0, 840: 12.0},
                           "fa-leso": {300: 0.0, 600: 0.0, 840: 0.0}},
    "fa_leso_ripple_deg": 2.3,
    # Figs. 13-14: 5th / 7th harmonic of the estimated alpha back-EMF, set 1 (%)
    "harmonics_pct": {
        "fig13_300rpm_50pct": {"c-leso": (5.4, 5.9), "gi-leso": (3.6, 4.0),
                               "fa-leso": (0.8, 0.7)},
        "fig14_600rpm_40pct": {"c-leso": (4.1, 4.5), "gi-leso": (2.7, 2.9),
                               "fa-leso": (0.6, 0.7)}},
    # Fig. 15: VSD control, 600 rpm, 80 % load: "negligible"
    # Fig. 16: speed ramp 300-600-840-600-300 rpm: max speed error 13 rpm (all three),
    # FA-LESO max position error about 4.5 deg; Fig. 17: load step 0 -> 80 % at 600 rpm:
    # max speed error 5 rpm, FA-LESO max position error about 3.2 deg
    "ramp": {"speed_err_rpm": 13.0, "fa_leso_pos_err_deg": 4.5},
    "load_step": {"speed_err_rpm": 5.0, "fa_leso_pos_err_deg": 3.2},
}


def rpm_to_w(drive: pj.Drive, rpm: float) -> float:
    """Electrical speed (rad/s) of `rpm` (mechanical)."""
    return float(drive.motor.n_p) * 2 * math.pi * rpm / 60.0


def individual_set_drive(drive: pj.Drive | None = None) -> pj.Drive:
    """One three-phase set of a dual three-phase drive as a three-phase drive (li-fa-leso
    Sec. V-B, [6]): the per-set machine (`drive.motor.ab`, with its 5th and 7th back-EMF
    harmonics in the alpha-beta plane), half the rated torque."""
    drive = pj.preset("li_dtp") if drive is None else drive
    one = eqx.tree_at(lambda d: d.motor, drive, drive.three_phase_motor)
    return eqx.tree_at(lambda d: d.tau_rated, one, 0.5 * float(drive.tau_rated))


def steady_run(name: str, rpm: float, load_pu: float = 0.0, *, drive=None, t_end=0.4,
               motor=None, T_s=T_S, dual=None, **design):
    """Current control at an imposed speed `rpm` with $i_q$ = `load_pu` p.u. of the rated
    current, the observer `name` in the loop (its model `motor`, default the drive's);
    `dual` as in `FOC.from_drive` (dual three-phase drives). Returns `(observer,
    Trajectory)`."""
    drive = pj.preset("li_dtp") if drive is None else drive
    w = rpm_to_w(drive, rpm)
    obs = make_observer(name, drive, motor=motor, **design)
    sc = pj.Scenario(t_end=t_end, w_m_imposed=pj.Profile.constant(w),
                     i_d_ref=pj.Profile.constant(0.0),
                     i_q_ref=pj.Profile.constant(load_pu * float(drive.base.I_b)))
    foc = pj.FOC.from_drive(drive, dual=dual)
    return obs, pj.simulate(drive, foc, obs, sc, T_s=T_s, w_m0=w)


def position_error(name: str, rpm: float, *, t_end=1.5, **kw) -> dict:
    """Figs. 10-12: mean and peak-to-peak angle error (deg) over the last 0.1 s, and the
    closed form $-\\arg G(j\\omega)$ (deg) of the observer's transfer function. The
    default 1.5 s lets the GI-LESO's lightly damped resonant mode (decay rate about
    10 1/s with Table II's $\\omega_c = \\pi$) die out; the C-LESO and FA-LESO settle
    within 0.3 s."""
    obs, traj = steady_run(name, rpm, t_end=t_end, **kw)
    n = int(round(0.1 / T_S))
    err = np.degrees(np.asarray(traj.theta_err)[-n:])
    w = float(traj.w_m[-1])
    G = complex(obs.transfer_function(1j * w, w))
    return {"mean_deg": float(err.mean()), "p2p_deg": float(err.max() - err.min()),
            "closed_form_deg": -math.degrees(np.angle(G)),
            "published_deg": PUBLISHED["position_error_deg"][name].get(int(rpm))}


def harmonic_content(e_alpha, w, T_s=T_S, orders=(5, 7)) -> dict:
    """Harmonics `orders` of the real signal `e_alpha` in % of its fundamental at the
    electrical speed `w` (rad/s): single-bin DFTs over the largest whole number of
    fundamental periods at the end of the record."""
    x = np.asarray(e_alpha, float)
    period = 2 * math.pi / abs(w) / T_s
    n_per = int(len(x) // period)
    n = int(round(n_per * period))
    x = x[-n:]
    k = np.arange(n)
    amp = lambda h: abs(np.sum(x * np.exp(-1j * h * abs(w) * k * T_s)))  # noqa: E731
    a1 = amp(1)
    return {h: 100.0 * amp(h) / a1 for h in orders}


def harmonics(name: str, rpm: float, load_pu: float, mode: str = "sets", **kw) -> dict:
    """Figs. 13-15: the 5th and 7th harmonic of the estimated alpha back-EMF (%), with
    individual-set control (`mode="sets"`, the observer on set 1) or VSD control
    (`mode="vsd"`, x-y currents regulated to zero; `"i_xy_rms"`: their rms over the
    analysed window, A), and the frequency-response prediction $|G_h| a_h$ (% of the
    fundamental estimate) where the harmonic reaches the observer."""
    if mode not in ("sets", "vsd"):
        raise ValueError(f"`harmonics(mode=...)` must be 'sets' or 'vsd'; got {mode!r}.")
    dtp = pj.preset("li_dtp")
    drive = individual_set_drive(dtp) if mode == "sets" else dtp
    kw.setdefault("dual", "vsd" if mode == "vsd" else None)
    obs, traj = steady_run(name, rpm, load_pu, drive=drive, **kw)
    w = rpm_to_w(drive, rpm)
    n = int(round(0.2 / T_S))
    e_a = np.asarray(traj.extras["e_ab_hat"])[-n:, 0]
    sim = harmonic_content(e_a, w)
    out = {"simulated_pct": sim}
    if mode == "vsd":
        i_xy = np.asarray(traj.i_xy)[-n:]
        out["i_xy_rms"] = float(np.sqrt(np.mean(np.sum(i_xy ** 2, -1))))
    if mode == "sets":
        harm = drive.three_phase_motor.harmonics
        G = pj.analysis.bemf_response(obs, w, (1, *harm.order), T_S)
        pred = {abs(h): 100.0 * float(a) * abs(G[k + 1]) / abs(G[0])
                for k, (h, a) in enumerate(zip(harm.order, np.asarray(harm.amplitude)))}
        out["response_pct"] = pred
    return out


def mismatch_offset(plant: pj.PMSMParams, model: pj.PMSMParams, w, i_dq_hat, G=1.0,
                    n_iter: int = 30) -> float:
    """The exact steady-state angle error $\\tilde\\theta$ (rad, true minus estimate) of a
    back-EMF observer with gain `G` (complex, $\\hat e/e$ at the fundamental) and model
    `model` (its $\\hat R_s$, $\\hat L_q$) on the machine `plant`, at electrical speed `w`
    (rad/s) and estimated-frame current `i_dq_hat` (A): the root of the module
    docstring's equation (generalised to any `G`), by Newton's method."""
    i_h = np.asarray(i_dq_hat, float)
    Ld, Lq, psi = float(plant.L_d), float(plant.L_q), float(plant.psi_f)
    dR = float(plant.R_s) - float(model.R_s)
    Lq_h = float(model.L_q)
    g = complex(G)
    sg = 1.0 if w >= 0 else -1.0

    def e_est(th):
        c, s = math.cos(th), math.sin(th)
        i_t = np.array([c * i_h[0] + s * i_h[1], -s * i_h[0] + c * i_h[1]])
        psi_t = np.array([Ld * i_t[0] + psi, Lq * i_t[1]])
        e_t = (w * np.array([-psi_t[1], psi_t[0]]) + dR * i_t
               - w * Lq_h * np.array([-i_t[1], i_t[0]]))
        e_c = g * complex(e_t[0], e_t[1])
        e_c *= complex(c, s)  # to the estimated frame: rotate by theta~
        return e_c

    th = -float(np.angle(g)) * sg
    for _ in range(n_iter):
        f = e_est(th).real * sg
        h = 1e-7
        d = (e_est(th + h).real * sg - f) / h
        th = th - f / d
    return float(pj.wrap_angle(th))


def mismatch_offset_printed(plant, model, w, i_dq_hat, which: str) -> float:
    """li-fa-leso (42) (`which="R_s"`) or (43) (`"L_q"`) with $\\Delta X = \\hat X - X$
    (the reading that gives the right sign; see the module docstring); rad."""
    i_d, i_q = (float(v) for v in i_dq_hat)
    E = w * float(plant.extended_flux(i_d))
    if which == "R_s":
        dR = float(model.R_s) - float(plant.R_s)
        return math.atan(-dR * i_d / (E - dR * i_q))
    if which == "L_q":
        dL = float(model.L_q) - float(plant.L_q)
        return math.atan(dL * i_q / (E / w - dL * i_d))
    raise ValueError(f"`which` must be 'R_s' or 'L_q'; got {which!r}.")


def mismatch_table(rpm=300.0, i_dq_pu=((0.0, 1.0), (-0.5, 1.0)), ratios=(0.5, 1.5),
                   name="fa-leso") -> list[dict]:
    """Fig. 18 and (42)-(43): for R_s and L_q model ratios `ratios` at `rpm` and the
    estimated-frame currents `i_dq_pu` (p.u.): the exact offset, the printed one and the
    stable equilibrium of `analysis.equilibria` (deg)."""
    drive = pj.preset("li_dtp")
    plant = drive.three_phase_motor
    w = rpm_to_w(drive, rpm)
    rows = []
    for i_pu in i_dq_pu:
        i = np.asarray(i_pu) * float(drive.base.I_b)
        for p in ("R_s", "L_q"):
            for r in ratios:
                model = eqx.tree_at(lambda m: getattr(m, p), plant, float(getattr(plant, p)) * r)
                obs = make_observer(name, drive, motor=model)
                G = complex(obs.transfer_function(1j * w, w))
                exact = mismatch_offset(plant, model, w, i, G)
                x = obs.designed_error(OperatingPoint(w, jnp.asarray(i)), plant)
                rows.append({"param": p, "ratio": r, "i_dq_pu": tuple(i_pu),
                             "exact_deg": math.degrees(exact),
                             "printed_deg": math.degrees(
                                 mismatch_offset_printed(plant, model, w, i, p)
                                 - float(np.angle(G))),
                             "equilibrium_deg": math.degrees(
                                 float(x[obs.coordinates.angle]))})
    return rows


def transient(name: str, kind: str = "ramp", *, t_scale: float = 1.0, drive=None):
    """Figs. 16-17: the speed loop on the observer's estimates. `kind="ramp"`: no load,
    300-600-840-600-300 rpm (ramps of 0.5 s x `t_scale`, holds of 0.5 s x `t_scale`);
    `"load_step"`: 600 rpm, load 0 -> 80 % -> 0. Returns the maxima of the speed error
    (rpm, mechanical) and of the position error (deg) after the start-up, with the
    published numbers."""
    drive = pj.preset("li_dtp") if drive is None else drive
    r2w = lambda r: rpm_to_w(drive, r)  # noqa: E731
    a = float(t_scale)
    if kind == "ramp":
        seq = [300, 600, 840, 600, 300]
        t, v = [0.0], [r2w(300)]
        for r in seq[1:]:
            t += [t[-1] + 0.5 * a, t[-1] + 1.0 * a]
            v += [r2w(r), r2w(r)]
        t_end = t[-1] + 0.5 * a
        sc = pj.Scenario(t_end=t_end, w_m_ref=pj.Profile(t, v))
        w0 = r2w(300)
        pub = PUBLISHED["ramp"]
    elif kind == "load_step":
        t_end = 1.5 * a
        tl = 0.8 * float(drive.tau_rated)
        sc = pj.Scenario(t_end=t_end, w_m_ref=pj.Profile.constant(r2w(600)),
                         tau_L=pj.Profile.steps([0.5 * a, 1.0 * a], [tl, 0.0]))
        w0 = r2w(600)
        pub = PUBLISHED["load_step"]
    else:
        raise ValueError(f"`kind` must be 'ramp' or 'load_step'; got {kind!r}.")
    obs = make_observer(name, drive)
    foc = pj.FOC.from_drive(drive, alpha_s=2 * math.pi * 5.0)
    traj = pj.simulate(drive, foc, obs, sc, T_s=T_S, w_m0=w0, save_every=10)
    k0 = int(0.4 * a / (10 * T_S))
    to_rpm = 60.0 / (2 * math.pi * float(drive.motor.n_p))
    dw = (np.asarray(traj.w_m) - np.asarray(traj.w_hat))[k0:] * to_rpm
    dth = np.degrees(np.asarray(traj.theta_err)[k0:])
    return {"max_speed_err_rpm": float(np.max(np.abs(dw))),
            "max_pos_err_deg": float(np.max(np.abs(dth))),
            "published": pub, "trajectory": traj}
