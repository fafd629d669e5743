r"""C emitter of the rotor-flux-vector observer of morawiec2023 (`RotorFluxObserver`,
"rotor-flux"): `RotorFluxObserver.step` line by line (`observers/_rotor_flux.py`).

Per step (k >= 1): the flux integrates the held voltage exactly and the measured
resistive drop by the trapezoid; the feedback (18)-(20), (29)-(33) is evaluated at
$t_{k-1}$ (Heun predictor), the speed by forward Euler, the angle with the mean of the
old and new speed plus $v_\theta$, and the flux correction held in the estimator frame
while it turns by $\Delta\theta$ (exact integral, sinc rule).
"""

from __future__ import annotations

from ..observers._rotor_flux import _SIGNS, RotorFluxObserver
from ._c import FLUX_STATE_INIT, CObserver, lit, model_defines, model_doc, scalar as _f


_FIELDS = (
    ("pmsm_real psi_ab[2]", "estimated stator flux, stationary frame (V s)"),
    ("pmsm_real theta", "estimated electrical angle, wrapped to (-pi, pi] (rad)"),
    ("pmsm_real w", "estimated electrical speed (rad/s)"),
    ("pmsm_real i_prev[2]", "current sampled at the previous instant (A, alpha-beta)"),
    ("int started", "0 until the first sample has been seen"),
)

def emit(observer: RotorFluxObserver, T_s: float) -> CObserver:
    """The `CObserver` of the rotor-flux observer (the gains do not depend on `T_s`)."""
    del T_s
    m = observer.motor
    c_alpha, c_lambda, k_c = _f(observer.c_alpha), _f(observer.c_lambda), _f(observer.k_c)
    c_theta, gamma = _f(observer.c_theta), _f(observer.gamma)
    k_theta = -_SIGNS[observer.theta_sign] * c_theta
    printed = observer.speed_sign == "printed"
    speed_law = ("dw = gamma * (cross - k_c * s_w)" if printed else
                 "dw = -gamma * (cross + k_c * sign(w) * s_w)")
    dw_c = ("    *dw = PMSM_GAMMA * (cross - PMSM_KC * s_w);" if printed else
            "    *dw = -PMSM_GAMMA * (cross + PMSM_KC * sgn * s_w);")
    helpers = f"""/* observer model and gains (SI) */
{model_defines(m)}
#define PMSM_CALPHA {lit(c_alpha)}
#define PMSM_CLAMBDA {lit(c_lambda)}
#define PMSM_KC {lit(k_c)}
#define PMSM_KTHETA {lit(k_theta)}
#define PMSM_GAMMA {lit(gamma)}

/* (12)-(13)/(36)-(38): entries of the inverse stationary-frame inductance (1/H) */
static void pmsm_l_functions(pmsm_real th, pmsm_real *L1, pmsm_real *L3, pmsm_real *L4)
{{
    pmsm_real c = PMSM_COS(th), s = PMSM_SIN(th);
    *L1 = c * c / PMSM_LD + s * s / PMSM_LQ;
    *L3 = PMSM_R(0.5) * (PMSM_R(1.0) / PMSM_LD - PMSM_R(1.0) / PMSM_LQ)
          * PMSM_SIN(PMSM_R(2.0) * th);
    *L4 = s * s / PMSM_LD + c * c / PMSM_LQ;
}}

/* rotor flux vector (5)-(6) / (10)-(11) at angle th and current i (V s) */
static void pmsm_rotor_flux(pmsm_real th, const pmsm_real i[2], pmsm_real lam[2])
{{
    pmsm_real L0 = PMSM_R(0.5) * (PMSM_LD + PMSM_LQ);
    pmsm_real L2 = PMSM_R(0.5) * (PMSM_LD - PMSM_LQ);
    pmsm_real r = PMSM_LD / PMSM_LQ;
    pmsm_real c2 = PMSM_COS(PMSM_R(2.0) * th), s2 = PMSM_SIN(PMSM_R(2.0) * th);
    pmsm_real ia2 = i[0] * c2 + i[1] * s2;   /* (39) */
    pmsm_real ib2 = -i[0] * s2 + i[1] * c2;  /* (40) */
    lam[0] = r * PMSM_PSIF * PMSM_COS(th) - (PMSM_R(1.0) - r) * (L0 * ia2 + L2 * i[0]);
    lam[1] = r * PMSM_PSIF * PMSM_SIN(th) + (PMSM_R(1.0) - r) * (L0 * ib2 - L2 * i[1]);
}}

/* stator flux L_ab(th) i + psi_f e^(th J) [1, 0] (V s) */
static void pmsm_stator_flux(pmsm_real th, const pmsm_real i[2], pmsm_real psi[2])
{{
    pmsm_real L0 = PMSM_R(0.5) * (PMSM_LD + PMSM_LQ);
    pmsm_real L2 = PMSM_R(0.5) * (PMSM_LD - PMSM_LQ);
    pmsm_real c2 = PMSM_COS(PMSM_R(2.0) * th), s2 = PMSM_SIN(PMSM_R(2.0) * th);
    psi[0] = (L0 + L2 * c2) * i[0] + L2 * s2 * i[1] + PMSM_PSIF * PMSM_COS(th);
    psi[1] = L2 * s2 * i[0] + (L0 - L2 * c2) * i[1] + PMSM_PSIF * PMSM_SIN(th);
}}

/* the observer's right-hand side at (th, w, psi) and the measured current i:
   flux correction c (V), frame speed wf (rad/s), dw/dt (rad/s^2) */
static void pmsm_rates(pmsm_real th, pmsm_real w, const pmsm_real psi[2],
                       const pmsm_real i[2], pmsm_real c[2], pmsm_real *wf, pmsm_real *dw)
{{
    pmsm_real L1, L3, L4, pa, pb, i_hat[2], e[2], lam_hat[2], lam[2];
    pmsm_real v_a, v_b, cr, dt, th_lam, v_th, cross, s_w, sgn;
    pmsm_real L0 = PMSM_R(0.5) * (PMSM_LD + PMSM_LQ);
    pmsm_real L2 = PMSM_R(0.5) * (PMSM_LD - PMSM_LQ);
    pmsm_real c2 = PMSM_COS(PMSM_R(2.0) * th), s2 = PMSM_SIN(PMSM_R(2.0) * th);
    pmsm_real La, Lab, Lb;
    pmsm_l_functions(th, &L1, &L3, &L4);
    /* current of the estimated flux */
    pa = psi[0] - PMSM_PSIF * PMSM_COS(th);
    pb = psi[1] - PMSM_PSIF * PMSM_SIN(th);
    i_hat[0] = L1 * pa + L3 * pb;
    i_hat[1] = L3 * pa + L4 * pb;
    e[0] = i_hat[0] - i[0];  /* (16) */
    e[1] = i_hat[1] - i[1];
    pmsm_rotor_flux(th, i_hat, lam_hat);  /* (10)-(11) */
    pmsm_rotor_flux(th, i, lam);          /* (5)-(6) at theta_hat */
    v_a = -PMSM_CALPHA * PMSM_RS * L1 * e[0] + PMSM_CLAMBDA * w / PMSM_LD * lam_hat[1] * e[0];
    v_b = -PMSM_CALPHA * PMSM_RS * L4 * e[1] - PMSM_CLAMBDA * w / PMSM_LD * lam_hat[0] * e[1];
    /* (30)-(31): atan2 of cross and dot products */
    cr = lam[0] * lam_hat[1] - lam[1] * lam_hat[0];
    dt = lam[0] * lam_hat[0] + lam[1] * lam_hat[1];
    th_lam = PMSM_ATAN2(cr, dt);
    v_th = PMSM_KTHETA * th_lam;  /* (29) */
    cross = (lam_hat[1] * e[0] - lam_hat[0] * e[1]) / PMSM_LD;
    s_w = (lam_hat[0] * e[0] + lam_hat[1] * e[1]) / PMSM_LD;  /* (33) */
    sgn = w > PMSM_R(0.0) ? PMSM_R(1.0) : (w < PMSM_R(0.0) ? PMSM_R(-1.0) : PMSM_R(0.0));
    (void)sgn;
{dw_c}
    /* correction: R_s (i - i_hat) + L_ab(th) v + v_th d psi_hat / d th */
    La = L0 + L2 * c2;
    Lab = L2 * s2;
    Lb = L0 - L2 * c2;
    c[0] = PMSM_RS * (i[0] - i_hat[0]) + (La * v_a + Lab * v_b)
           + v_th * (PMSM_R(2.0) * L2 * (-s2 * i_hat[0] + c2 * i_hat[1])
                     - PMSM_PSIF * PMSM_SIN(th));
    c[1] = PMSM_RS * (i[1] - i_hat[1]) + (Lab * v_a + Lb * v_b)
           + v_th * (PMSM_R(2.0) * L2 * (c2 * i_hat[0] + s2 * i_hat[1])
                     + PMSM_PSIF * PMSM_COS(th));
    *wf = w + v_th;
}}
"""
    step = """    pmsm_real psi[2], theta, w;
    int j;
    if (!s->started) {
        /* first sample: the flux of the measured current at the initial angle */
        pmsm_stator_flux(s->theta, i_ab, psi);
        theta = s->theta;
        w = s->w;
    } else {
        pmsm_real c1[2], wf1, dw1, dth, half, x, sinc, corr[2];
        pmsm_rates(s->theta, s->w, s->psi_ab, s->i_prev, c1, &wf1, &dw1);
        w = s->w + PMSM_OBS_T_S * dw1;
        dth = PMSM_OBS_T_S * (wf1 - s->w + PMSM_R(0.5) * (s->w + w));
        half = PMSM_R(0.5) * dth;
        x = half / PMSM_PI;
        sinc = x == PMSM_R(0.0) ? PMSM_R(1.0) : PMSM_SIN(PMSM_PI * x) / (PMSM_PI * x);
        pmsm_rotate(c1, half, corr);
        for (j = 0; j < 2; j++)
            psi[j] = s->psi_ab[j] + PMSM_OBS_T_S * u_ab_prev[j]
                     - (PMSM_R(0.5) * PMSM_OBS_T_S * PMSM_RS) * (s->i_prev[j] + i_ab[j])
                     + (PMSM_OBS_T_S * sinc) * corr[j];
        theta = pmsm_wrap(s->theta + dth);
        /* a step that leaves the state non-finite (a design beyond the sampling rate's
           limit running away) is not taken: the estimate stays finite, frozen */
        if (!(isfinite(psi[0]) && isfinite(psi[1]) && isfinite(w) && isfinite(dth))) {
            psi[0] = s->psi_ab[0];
            psi[1] = s->psi_ab[1];
            w = s->w;
            theta = s->theta;
        }
    }
    for (j = 0; j < 2; j++) {
        s->psi_ab[j] = psi[j];
        s->i_prev[j] = i_ab[j];
    }
    s->theta = theta;
    s->w = w;
    s->started = 1;
    *theta_hat = theta;
    *w_hat = w;"""
    title = "rotor-flux-vector adaptive observer, morawiec2023 (7)-(14), (18)-(20), (29)-(33)"
    doc = (
        f"Observer: rotor-flux, {title}.",
        "M. Morawiec, A. Lewicki, I. C. Odeh, IEEE Trans. Ind. Electron. 70(12), 2023,",
        "doi:10.1109/TIE.2023.3250851.",
        model_doc(m),
        f"Gains: c_alpha = {c_alpha!r}, c_lambda = {c_lambda!r} 1/A, k_c = {k_c!r},",
        f"  c_theta = {c_theta!r} 1/s (v_theta = {k_theta!r} theta_lambda, sign "
        f"{observer.theta_sign}), gamma = {gamma!r} 1/(s^2 A^2);",
        f"  speed law ({observer.speed_sign}): {speed_law}.",
        "State psi_ab is the stator flux; the current estimate is i_hat = L_ab(theta)^-1",
        "(psi - psi_f e^(theta J)[1,0]).",
        "Step (k >= 1), rates (c, w_f, dw) from the state and i_(k-1):",
        "  w     += T_s dw",
        "  dth    = T_s (w_f - w_old + (w_old + w)/2)",
        "  psi   += T_s u_prev - T_s R_s (i_prev + i_k)/2 + T_s sinc(dth/2) e^(dth/2 J) c",
        "  theta  = wrap(theta + dth)",
        "First sample: psi = L_ab(theta0) i_0 + psi_f e^(theta0 J)[1,0]; theta, w unchanged.",
    )
    return CObserver(name="rotor-flux", title=title, doc=doc, fields=_FIELDS,
                     helpers=helpers, init=FLUX_STATE_INIT, step=step)
