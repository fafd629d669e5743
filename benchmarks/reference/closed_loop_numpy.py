"""Plain-NumPy reference of the closed-loop benchmark (`benchmarks/throughput/simulate.py`).

The same discrete algorithm as `pmsmjax.simulate` for sensored speed control of a
three-phase PMSM without flux harmonics (and as `closed_loop.c`): batched arrays over
drives (shape (B,)) and a Python loop over the sampling instants. See `closed_loop.c` for
the step; `params` is the dict `benchmarks.throughput.simulate.reference_params` builds
from the drive and the controller.
"""

from __future__ import annotations

import numpy as np


def _wrap_angle(th):
    w = np.remainder(th + np.pi, 2 * np.pi) - np.pi
    return np.where(w <= -np.pi, w + 2 * np.pi, w)


def _field(p, i_d, i_q, th, w, u_a, u_b, tau_l):
    c, s = np.cos(th), np.sin(th)
    u_d, u_q = c * u_a + s * u_b, -s * u_a + c * u_b
    psi_d, psi_q = p["L_d"] * i_d + p["psi_f"], p["L_q"] * i_q
    di_d = (u_d - p["R_s"] * i_d + w * psi_q) / p["L_d"]
    di_q = (u_q - p["R_s"] * i_q - w * psi_d) / p["L_q"]
    tau = 1.5 * p["n_p"] * (psi_d * i_q - psi_q * i_d)
    dw = p["n_p"] * (tau - p["B"] * w / p["n_p"] - tau_l) / p["J"]
    return di_d, di_q, w, dw


def simulate(p: dict, w_final, n_steps: int, dtype=np.float64):
    """Run `len(w_final)` drives for `n_steps` periods; returns (B, 6) final
    `(i_d, i_q, theta, w_m, ise_w, ok)`."""
    w_final = np.asarray(w_final, dtype)
    # scalars of the run dtype, so float32 runs stay float32
    p = {k: (dtype(v) if isinstance(v, float) else v) for k, v in p.items()}
    T_s = p["T_s"]
    z = np.zeros_like(w_final)
    i_d, i_q, th, w = z.copy(), z.copy(), z.copy(), z.copy()
    x_s, x_d, x_q, ise = z.copy(), z.copy(), z.copy(), z.copy()
    ok = np.ones(w_final.shape, bool)
    kp_s = dtype(2.0 * p["alpha_s"] * p["J_over_np"])
    ki_s = dtype(p["alpha_s"] ** 2 * p["J_over_np"])
    Kp_d, Kp_q = p["alpha_c"] * p["cL_d"], p["alpha_c"] * p["cL_q"]
    Ki = p["alpha_c"] * p["cR_s"]
    h = dtype(p["T_s"] / p["n_sub"])
    i_d_ref = p["i_d_ref"]
    iq_den = p["k_tau"] * (p["cpsi_f"] + (p["cL_d"] - p["cL_q"]) * i_d_ref)
    i_q_max = np.sqrt(max(p["i_max"] ** 2 - i_d_ref ** 2, 0.0)).astype(dtype)
    half, sixth, third = dtype(0.5), dtype(1 / 6), dtype(1 / 3)
    for k in range(n_steps):
        t = dtype(k) * T_s
        w_ref = w_final if t >= p["t_ramp"] else (t / p["t_ramp"]) * w_final
        tau_l = p["tau_load"] if t >= p["t_load"] else dtype(0.0)
        # sensing, sensored observer
        c0, s0 = np.cos(th), np.sin(th)
        i_a, i_b = c0 * i_d - s0 * i_q, s0 * i_d + c0 * i_q
        th_hat, w_hat = _wrap_angle(th), w
        ch, sh = np.cos(th_hat), np.sin(th_hat)
        i_cd, i_cq = ch * i_a + sh * i_b, -sh * i_a + ch * i_b
        # speed PI
        e_w = w_ref - w_hat
        tau = kp_s * e_w + x_s
        tau_lim = np.clip(tau, -p["tau_max"], p["tau_max"])
        x_s = x_s + T_s * ki_s * (e_w + (tau_lim - tau) / kp_s)
        i_q_ref = np.clip(tau_lim / iq_den, -i_q_max, i_q_max)
        # current PI with decoupling, limit, anti-windup
        e_d, e_q = i_d_ref - i_cd, i_q_ref - i_cq
        psi_d, psi_q = p["cL_d"] * i_cd + p["cpsi_f"], p["cL_q"] * i_cq
        u_d = Kp_d * e_d + x_d - w_hat * psi_q
        u_q = Kp_q * e_q + x_q + w_hat * psi_d
        n2 = u_d * u_d + u_q * u_q
        n = np.sqrt(np.where(n2 > 0, n2, 1.0))
        sc = np.where(n > p["u_max"], p["u_max"] / n, 1.0)
        u_dl, u_ql = u_d * sc, u_q * sc
        x_d = x_d + T_s * Ki * (e_d + (u_dl - u_d) / Kp_d)
        x_q = x_q + T_s * Ki * (e_q + (u_ql - u_q) / Kp_q)
        ang = th_hat + half * w_hat * T_s
        ca, sa = np.cos(ang), np.sin(ang)
        u_a, u_b = ca * u_dl - sa * u_ql, sa * u_dl + ca * u_ql
        ise = ise + T_s * (w_ref - w) ** 2
        # plant: RK4
        y = (i_d, i_q, th, w)
        for _ in range(p["n_sub"]):
            k1 = [h * f for f in _field(p, *y, u_a, u_b, tau_l)]
            k2 = [h * f for f in _field(p, *(a + half * b for a, b in zip(y, k1)),
                                        u_a, u_b, tau_l)]
            k3 = [h * f for f in _field(p, *(a + half * b for a, b in zip(y, k2)),
                                        u_a, u_b, tau_l)]
            k4 = [h * f for f in _field(p, *(a + b for a, b in zip(y, k3)),
                                        u_a, u_b, tau_l)]
            y = tuple(a + (b1 * sixth + b2 * third + b3 * third + b4 * sixth)
                      for a, b1, b2, b3, b4 in zip(y, k1, k2, k3, k4))
        good = ok & np.isfinite(y[0]) & np.isfinite(y[1]) & np.isfinite(y[2]) \
            & np.isfinite(y[3]) & (y[0] ** 2 + y[1] ** 2 < p["i_bound"] ** 2) \
            & (np.abs(y[3]) < p["w_bound"])
        i_d, i_q, th, w = (np.where(good, a, b) for a, b in zip(y, (i_d, i_q, th, w)))
        ok = good
    return np.stack([i_d, i_q, th, w, ise, ok.astype(dtype)], -1)
