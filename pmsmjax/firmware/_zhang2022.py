r"""C emitter of the zhang2022 flux observers: `ESOObserver` (fal feedback),
`LESOObserver` (linear feedback) and `AFOObserver` (PI speed law (53)), with the gains of
their `design` (`ESODesign` schedules, `FixedGains`, tuned `TabulatedDesign`).

The C step is `AbstractFluxObserver.step` line by line (`observers/_eso.py`): at the
first sample the flux is initialised from the model, afterwards the error (10d) at
$t_{k-1}$, the gains (17)/(25) (or (53)) scheduled at the speed state, the flux update
(exact ZOH voltage, trapezoidal resistive drop, rotating-frame exact correction
$T_s\,\mathrm{sinc}(\omega_f T_s/2)\,e^{(\hat\theta+\omega_f T_s/2)J} G_1 f(e)$), the
angle and speed updates.
"""

from __future__ import annotations

import numpy as np

from .._data._gains_table import TabulatedDesign
from ..observers import AFOObserver, ESODesign, ESOObserver, FixedGains, LESOObserver
from ._c import FLUX_STATE_INIT, CObserver, lit, model_defines, model_doc, scalar as _f


_FIELDS = (
    ("pmsm_real psi_ab[2]", "estimated stator flux, stationary frame (V s)"),
    ("pmsm_real theta", "estimated electrical angle, wrapped to (-pi, pi] (rad)"),
    ("pmsm_real w", "ESO/LESO: extended state w_hat; AFO: integral part x_I of the PI "
                    "speed law zhang2022 (53) (rad/s)"),
    ("pmsm_real i_prev[2]", "current sampled at the previous instant (A, alpha-beta)"),
    ("int started", "0 until the first sample has been seen"),
)

def _schedule_c(design) -> tuple[str, list[str]]:
    """C function `pmsm_gains(w0, pa, G1, g2, g3, kp_ki)` for the design, and doc lines."""
    head = ("static void pmsm_gains(pmsm_real w0, const pmsm_real pa[2], pmsm_real G1[4],\n"
            "                       pmsm_real g2[2], pmsm_real g3[2], pmsm_real pi_k[2])\n{\n")
    if isinstance(design, FixedGains):
        G1 = np.asarray(design.gains.G1, float).reshape(4)
        g2 = np.asarray(design.gains.g2, float).reshape(2)
        g3 = np.asarray(design.gains.g3, float).reshape(2)
        body = ["    (void)w0;", "    (void)pa;"]
        body += [f"    G1[{j}] = {lit(G1[j])};" for j in range(4)]
        body += [f"    g2[{j}] = {lit(g2[j])};" for j in range(2)]
        body += [f"    g3[{j}] = {lit(g3[j])};" for j in range(2)]
        body += [f"    pi_k[0] = {lit(design.k_p)};", f"    pi_k[1] = {lit(design.k_i)};"]
        doc = ["Gains: frozen (FixedGains, zhang2022 Fig. 11): G1 (1/s, row-major 2x2), "
               "g2, g3, k_p, k_i constants."]
        return head + "\n".join(body) + "\n}\n", doc
    if isinstance(design, ESODesign):
        sch = design.schedule
        body = []
        if sch == "zhang38":
            body += [f"    pmsm_real zeta1 = {lit(design.zeta1_scale)} * (PMSM_R(1.5) + "
                     f"PMSM_FABS(w0) / {lit(design.w_rated)});",
                     f"    pmsm_real w1 = {lit(design.decay_scale)} * PMSM_R(1.5) * "
                     f"PMSM_FABS(w0) / zeta1;"]
        elif sch == "fixed_ratio":
            body += [f"    pmsm_real zeta1 = {lit(design.zeta1)};",
                     f"    pmsm_real w1 = {lit(design.ratio)} * PMSM_FABS(w0);"]
        else:
            body += [f"    pmsm_real zeta1 = {lit(design.zeta1)};",
                     f"    pmsm_real w1 = {lit(design.w1)};"]
        body += [f"    pmsm_real zeta2 = {lit(design.zeta2)};",
                 f"    pmsm_real w2 = {lit(design.w2)};",
                 f"    pmsm_real n2 = {lit(design.n2)};",
                 f"    pmsm_real n3 = {lit(design.n3)};"]
        w_min = _f(design.w_min) if sch == "fixed_w1" else 0.0
        if sch == "zhang38":
            what = (f"zeta1 = k_zeta (1.5 + |w0|/w_rated), w1 = k_sigma 1.5 |w0|/zeta1 "
                    f"(zhang2022 (38), w_rated = {_f(design.w_rated)!r} rad/s, k_zeta = "
                    f"{_f(design.zeta1_scale)!r}, k_sigma = {_f(design.decay_scale)!r})")
        elif sch == "fixed_ratio":
            what = f"zeta1 = {_f(design.zeta1)!r}, w1 = {_f(design.ratio)!r} |w0|"
        else:
            what = (f"zeta1 = {_f(design.zeta1)!r}, w1 = {_f(design.w1)!r} rad/s, |w0| "
                    f"clamped to w_min = {w_min!r} rad/s in (17)")
        doc = [f"Gains: ESODesign, schedule {sch}: {what};",
               f"  zeta2 = {_f(design.zeta2)!r}, w2 = {_f(design.w2)!r} rad/s, "
               f"n2 = {_f(design.n2)!r}, n3 = {_f(design.n3)!r}."]
    elif isinstance(design, TabulatedDesign):
        w = np.asarray(design.w_m, float)
        n = w.size
        cols = ("w_m", "zeta1", "w1", "zeta2", "w2", "nu2", "nu3")
        tables = []
        for c in cols:
            vals = ", ".join(lit(x) for x in np.asarray(getattr(design, c), float))
            tables.append(f"    static const pmsm_real t_{c}[{n}] = {{{vals}}};")
        body = tables + [
            "    pmsm_real zeta1, w1, zeta2, w2, nu2, nu3, pn, n2, n3;",
            "    int k = 1;",
            "    /* jnp.interp: clamp outside the table, linear inside */",
            f"    while (k < {n - 1} && w0 >= t_w_m[k]) k++;",
            "    if (w0 <= t_w_m[0]) {",
            "        zeta1 = t_zeta1[0]; w1 = t_w1[0]; zeta2 = t_zeta2[0];",
            "        w2 = t_w2[0]; nu2 = t_nu2[0]; nu3 = t_nu3[0];",
            f"    }} else if (w0 >= t_w_m[{n - 1}]) {{",
            f"        zeta1 = t_zeta1[{n - 1}]; w1 = t_w1[{n - 1}]; zeta2 = t_zeta2[{n - 1}];",
            f"        w2 = t_w2[{n - 1}]; nu2 = t_nu2[{n - 1}]; nu3 = t_nu3[{n - 1}];",
            "    } else {",
            "        pmsm_real r = (w0 - t_w_m[k - 1]) / (t_w_m[k] - t_w_m[k - 1]);",
            "        zeta1 = t_zeta1[k - 1] + r * (t_zeta1[k] - t_zeta1[k - 1]);",
            "        w1 = t_w1[k - 1] + r * (t_w1[k] - t_w1[k - 1]);",
            "        zeta2 = t_zeta2[k - 1] + r * (t_zeta2[k] - t_zeta2[k - 1]);",
            "        w2 = t_w2[k - 1] + r * (t_w2[k] - t_w2[k - 1]);",
            "        nu2 = t_nu2[k - 1] + r * (t_nu2[k] - t_nu2[k - 1]);",
            "        nu3 = t_nu3[k - 1] + r * (t_nu3[k] - t_nu3[k - 1]);",
            "    }",
            "    pn = PMSM_SQRT(pa[0] * pa[0] + pa[1] * pa[1]);",
            "    n2 = nu2 * PMSM_R(2.0) * zeta2 * w2 / pn;",
            "    n3 = nu3 * w2 * w2 / pn;",
        ]
        w_min = 0.0
        doc = [f"Gains: tuned table over speed ({n} rows, w_m from {w[0]!r} to {w[-1]!r} "
               "rad/s) of zeta1, w1, zeta2, w2, nu2, nu3,",
               "  interpolated linearly in the speed state (held at the end rows), then "
               "zhang2022 (17), (25) with n2 = nu2 2 zeta2 w2/|psi_a|, n3 = nu3 w2^2/|psi_a|."]
    else:
        raise ValueError(f"export-c supports the designs ESODesign, FixedGains and a tuned "
                         f"gains table; got {type(design).__name__}.")
    if w_min:
        body.append(f"    pmsm_real w0c = PMSM_FABS(w0) < {lit(w_min)} ? "
                    f"(w0 < PMSM_R(0.0) ? -{lit(w_min)} : {lit(w_min)}) : w0;")
    else:
        body.append("    pmsm_real w0c = w0;")
    body += [
        "    pmsm_real nrm2 = pa[0] * pa[0] + pa[1] * pa[1];",
        "    /* (17): G1 = (2 zeta1 w1 pa pa^T + c J pa pa^T)/|pa|^2, c = w1^2/w0 - w0 */",
        "    pmsm_real c = (w0c == PMSM_R(0.0) ? PMSM_R(0.0) : w1 * w1 / w0c) - w0;",
        "    pmsm_real jpa[2];",
        "    pmsm_real row[2], nul[2], rn;",
        "    int r, q;",
        "    jpa[0] = -pa[1];",
        "    jpa[1] = pa[0];",
        "    for (r = 0; r < 2; r++)",
        "        for (q = 0; q < 2; q++)",
        "            G1[2 * r + q] = (PMSM_R(2.0) * zeta1 * w1 * (pa[r] * pa[q])",
        "                             + c * (jpa[r] * pa[q])) / nrm2;",
        "    /* (25) plus the null space: g2 = 2 zeta2 w2 row + n2 nul, g3 = w2^2 row + n3 nul */",
        "    row[0] = pa[1] / nrm2;",
        "    row[1] = -pa[0] / nrm2;",
        "    rn = PMSM_SQRT(nrm2);",
        "    nul[0] = pa[0] / rn;",
        "    nul[1] = pa[1] / rn;",
        "    for (r = 0; r < 2; r++) {",
        "        g2[r] = PMSM_R(2.0) * zeta2 * w2 * row[r] + n2 * nul[r];",
        "        g3[r] = w2 * w2 * row[r] + n3 * nul[r];",
        "    }",
        "    /* (53): k_p = 2 zeta2 w2/psi_ad0, k_i = w2^2/psi_ad0 */",
        "    pi_k[0] = PMSM_R(2.0) * zeta2 * w2 / pa[0];",
        "    pi_k[1] = w2 * w2 / pa[0];",
    ]
    # C99 allows declarations after statements; keep them at the top of blocks anyway
    # where it matters for readability only.
    return head + "\n".join(body) + "\n}\n", doc


#: The new state written back at the end of every zhang2022 family's step.
_STORE_STATE = [
    "    for (j = 0; j < 2; j++) {",
    "        s->psi_ab[j] = psi[j];",
    "        s->i_prev[j] = i_ab[j];",
    "    }",
    "    s->theta = theta;",
    "    s->w = w;",
    "    s->started = 1;",
]


def emit(observer, T_s: float) -> CObserver:
    """The `CObserver` of an ESO, LESO or AFO (the gains do not depend on `T_s`)."""
    del T_s
    if type(observer) not in (ESOObserver, LESOObserver, AFOObserver):
        raise ValueError(f"export-c supports the observers eso, leso, afo; got "
                         f"{type(observer).__name__}.")
    m = observer.motor
    gains_c, gains_doc = _schedule_c(observer.design)
    afo = isinstance(observer, AFOObserver)
    helpers = [
        "/* observer model: R_s (Ohm), L_d, L_q (H), psi_f (V s) */",
        model_defines(m),
        "",
        "/* model flux L i + psi_f in the frame at angle theta, from i_ab; also i_dq */",
        "static void pmsm_model_flux(const pmsm_real i_ab[2], pmsm_real theta,",
        "                            pmsm_real flux_dq[2], pmsm_real i_dq[2])",
        "{",
        "    pmsm_rotate(i_ab, -theta, i_dq);",
        "    flux_dq[0] = PMSM_LD * i_dq[0] + PMSM_PSIF;",
        "    flux_dq[1] = PMSM_LQ * i_dq[1];",
        "}",
        "",
        "/* error signal (10d) e = L i - psi + psi_f (V s), estimator frame; i_dq (A) */",
        "static void pmsm_error(const pmsm_real psi_ab[2], pmsm_real theta,",
        "                       const pmsm_real i_ab[2], pmsm_real e[2], pmsm_real i_dq[2])",
        "{",
        "    pmsm_real flux[2], psi_dq[2];",
        "    pmsm_model_flux(i_ab, theta, flux, i_dq);",
        "    pmsm_rotate(psi_ab, -theta, psi_dq);",
        "    e[0] = flux[0] - psi_dq[0];",
        "    e[1] = flux[1] - psi_dq[1];",
        "}",
        "",
        "/* auxiliary flux (7) psi_a = [(L_d - L_q) i_d + psi_f, -(L_d - L_q) i_q] */",
        "static void pmsm_psi_a(const pmsm_real i_dq[2], pmsm_real pa[2])",
        "{",
        "    pmsm_real dL = PMSM_LD - PMSM_LQ;",
        "    pa[0] = dL * i_dq[0] + PMSM_PSIF;",
        "    pa[1] = -dL * i_dq[1];",
        "}",
        "",
        gains_c,
    ]
    if isinstance(observer, ESOObserver):
        a, eta = _f(observer.a), _f(observer.eta)
        helpers += [
            "/* f(e) = eta^(1-a) fal(e; a, eta), zhang2022 (9) with footnote 1's scaling */",
            "static pmsm_real pmsm_feedback(pmsm_real e)",
            "{",
            f"    pmsm_real fe = PMSM_FABS(e) > {lit(eta)}",
            f"        ? (e > PMSM_R(0.0) ? PMSM_R(1.0) : PMSM_R(-1.0)) * "
            f"PMSM_POW(PMSM_FABS(e), {lit(a)})",
            f"        : e * {lit(eta ** (a - 1.0))};",
            f"    return fe * {lit(eta ** (1.0 - a))};",
            "}",
            "",
        ]
        fb = f"f(e) = eta^(1-a) fal(e) with a = {a!r}, eta = {eta!r} V s (zhang2022 (9))"
    elif not afo:
        helpers += ["static pmsm_real pmsm_feedback(pmsm_real e) { return e; }", ""]
        fb = "f(e) = e (linear ESO)"
    # the flux update common to the three observers
    flux_update = [
        "        /* flux: exact ZOH voltage, trapezoidal R_s i, correction held in the",
        "           estimator frame turning at w_f: T_s sinc(w_f T_s/2) e^((theta+w_f T_s/2)J) */",
        "        half = PMSM_R(0.5) * PMSM_OBS_T_S * w_f;",
        "        x = half / PMSM_PI;",
        "        sinc = x == PMSM_R(0.0) ? PMSM_R(1.0)",
        "                                 : PMSM_SIN(PMSM_PI * x) / (PMSM_PI * x);",
        "        pmsm_rotate(G1f, s->theta + half, corr);",
        "        for (j = 0; j < 2; j++)",
        "            psi[j] = s->psi_ab[j] + PMSM_OBS_T_S * u_ab_prev[j]",
        "                     - (PMSM_R(0.5) * PMSM_OBS_T_S * PMSM_RS) * (s->i_prev[j] + i_ab[j])",
        "                     + (PMSM_OBS_T_S * sinc) * corr[j];",
        "        theta = pmsm_wrap(s->theta + PMSM_OBS_T_S * w_f);",
    ]
    decl = ["    pmsm_real psi[2], theta, w;",
            "    pmsm_real e[2], i_dq[2], pa[2], G1[4], g2[2], g3[2], pi_k[2], f[2], G1f[2];",
            "    pmsm_real w_f, half, x, sinc, corr[2];",
            "    int j;",
            "    if (!s->started) {",
            "        /* first sample: flux from the model at the initial angle, e_0 = 0 */",
            "        pmsm_real flux[2];",
            "        pmsm_model_flux(i_ab, s->theta, flux, i_dq);",
            "        pmsm_rotate(flux, s->theta, psi);",
            "        theta = s->theta;",
            "        w = s->w;",
            "    } else {",
            "        pmsm_error(s->psi_ab, s->theta, s->i_prev, e, i_dq);",
            "        pmsm_psi_a(i_dq, pa);"]
    if afo:
        body = decl + [
            "        /* (53): k_p, k_i at the integral state; w_f = x_I - k_p e_q */",
            "        pmsm_gains(s->w, pa, G1, g2, g3, pi_k);",
            "        w_f = s->w - pi_k[0] * e[1];",
            "        /* G1 (17) scheduled on x_I too (observers/_eso.py, _flux_gain_speed) */",
            "        (void)f;",
            "        G1f[0] = G1[0] * e[0] + G1[1] * e[1];",
            "        G1f[1] = G1[2] * e[0] + G1[3] * e[1];",
        ] + flux_update + [
            "        w = s->w - PMSM_OBS_T_S * pi_k[1] * e[1];",
            "    }",
        ] + _STORE_STATE + [
            "    /* speed estimate: the PI output at t_k, x_I - k_p e_q(t_k) */",
            "    pmsm_error(psi, theta, i_ab, e, i_dq);",
            "    pmsm_psi_a(i_dq, pa);",
            "    pmsm_gains(w, pa, G1, g2, g3, pi_k);",
            "    *theta_hat = theta;",
            "    *w_hat = w - pi_k[0] * e[1];",
        ]
        fb = "linear feedback G1 e; speed law (53) w_f = x_I - k_p e_q, dx_I/dt = -k_i e_q"
        speed = ("w_hat = x_I - k_p e_q at t_k (the PI output, zhang2022 (53)); the flux "
                 "gain G1 is scheduled on x_I")
    else:
        body = decl + [
            "        pmsm_gains(s->w, pa, G1, g2, g3, pi_k);",
            "        (void)pi_k;",
            "        f[0] = pmsm_feedback(e[0]);",
            "        f[1] = pmsm_feedback(e[1]);",
            "        w_f = s->w + (g2[0] * f[0] + g2[1] * f[1]);",
            "        G1f[0] = G1[0] * f[0] + G1[1] * f[1];",
            "        G1f[1] = G1[2] * f[0] + G1[3] * f[1];",
        ] + flux_update + [
            "        w = s->w + PMSM_OBS_T_S * (g3[0] * f[0] + g3[1] * f[1]);",
            "    }",
        ] + _STORE_STATE + [
            "    *theta_hat = theta;",
            "    *w_hat = w;",
        ]
        speed = "w_hat = the extended state w (not the frame speed w_f)"
    name = {ESOObserver: "eso", LESOObserver: "leso", AFOObserver: "afo"}[type(observer)]
    title = {"eso": "nonlinear ESO flux observer, zhang2022 (10a)-(10e), fal (9)",
             "leso": "linear ESO flux observer, zhang2022 (10) with f(e) = e",
             "afo": "adaptive full-order observer [21] with zhang2022's speed law (53)"}[name]
    doc = (
        f"Observer: {name}, {title}.",
        "M. Zhang, B. Xia, J. Zhang, IEEE Trans. Energy Convers. 37(4), 2022,",
        "doi:10.1109/TEC.2022.3177707.",
        model_doc(m),
        f"Feedback: {fb}.",
        *gains_doc,
        *(() if isinstance(observer.design, FixedGains) else (
            "Gains are evaluated every step at the speed state w and the previous "
            "current",
            "in the estimator frame (psi_a (7) from i_dq).")),
        "Step (k >= 1), with e, i_dq the error (10d) at t_(k-1):",
        *(("  w_f   = x_I - k_p e_q                       (frame speed, rad/s)",
           "  psi  += T_s u_prev - T_s R_s (i_prev + i_k)/2",
           "          + T_s sinc(w_f T_s/2) exp((theta + w_f T_s/2) J) G1 e",
           "  theta = wrap(theta + T_s w_f);  x_I -= T_s k_i e_q") if afo else
          ("  w_f   = w + g2 . f(e)                        (frame speed, rad/s)",
           "  psi  += T_s u_prev - T_s R_s (i_prev + i_k)/2",
           "          + T_s sinc(w_f T_s/2) exp((theta + w_f T_s/2) J) G1 f(e)",
           "  theta = wrap(theta + T_s w_f);  w += T_s g3 . f(e)")),
        f"Speed output: {speed}.",
        "First sample: psi = exp(theta0 J)(L i_0 + psi_f) in the frame of theta0; theta, w",
        "unchanged.",
    )
    return CObserver(name=name, title=title, doc=doc, fields=_FIELDS,
                     helpers="\n".join(helpers), init=FLUX_STATE_INIT, step="\n".join(body))
