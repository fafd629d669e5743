r"""C emitter of the reduced-order flux observer (`ReducedOrderObserver`,
"reduced-order"; Hinkkanen et al. 2018, PM-flux adaptation Tuovinen et al. 2018):
`ReducedOrderObserver.step` line by line (`observers/_reduced_order.py`).

Per step (k >= 1), from the state and the current $i_{k-1}$ in the estimated frame at
$\hat\theta_{k-1}$: $e = \psi_s(i) - \hat\psi$, $\psi_a$, $\varepsilon =
-\mathrm{Im}\{e/\psi_a\}$, $\omega_c = \hat\omega + 2\alpha_o\varepsilon$, the flux
correction $2k_1\psi_a\mathrm{Re}\{e/\psi_a\}$ ($k_1 = \sigma_0 + \zeta_\infty
|\hat\omega|$); the flux integrates the held voltage exactly and the resistive drop by
the trapezoid, the correction held in the estimated frame while it turns (sinc rule); the
angle, the speed ($\alpha_o^2\varepsilon$) and the PM-flux correction
($-k_f|\psi_a|\mathrm{Re}\{e/\psi_a\}$) by forward Euler.
"""

from __future__ import annotations

from ..observers import ReducedOrderObserver
from ._c import CObserver, lit, model_defines, model_doc, scalar as _f


_FIELDS = (
    ("pmsm_real psi_ab[2]", "estimated stator flux, stationary frame (V s)"),
    ("pmsm_real theta", "estimated electrical angle, wrapped to (-pi, pi] (rad)"),
    ("pmsm_real w", "estimated electrical speed, the speed-adaptation state (rad/s)"),
    ("pmsm_real dpsi_f", "adapted correction to the model's PM flux (V s)"),
    ("pmsm_real i_prev[2]", "current sampled at the previous instant (A, alpha-beta)"),
    ("int started", "0 until the first sample has been seen"),
)

_INIT = """    s->psi_ab[0] = PMSM_R(0.0);
    s->psi_ab[1] = PMSM_R(0.0);
    s->theta = pmsm_wrap(theta0);
    s->w = w0;
    s->dpsi_f = PMSM_R(0.0);
    s->i_prev[0] = PMSM_R(0.0);
    s->i_prev[1] = PMSM_R(0.0);
    s->started = 0;"""

_STEP = """    pmsm_real psi[2], theta, w, dpsi_f, i_dq[2];
    int j;
    if (!s->started) {
        /* first sample: the model flux at the measured current and the initial angle */
        pmsm_real flux[2];
        pmsm_rotate(i_ab, -s->theta, i_dq);
        flux[0] = PMSM_LD * i_dq[0] + (PMSM_PSIF + s->dpsi_f);
        flux[1] = PMSM_LQ * i_dq[1];
        pmsm_rotate(flux, s->theta, psi);
        theta = s->theta;
        w = s->w;
        dpsi_f = s->dpsi_f;
    } else {
        pmsm_real psi_dq[2], psi_f, e[2], pa[2], dL, n, re, im, eps, k1, w_c;
        pmsm_real coef, corr_dq[2], dpf, half, x, sinc, corr[2];
        pmsm_rotate(s->psi_ab, -s->theta, psi_dq);
        pmsm_rotate(s->i_prev, -s->theta, i_dq);
        psi_f = PMSM_PSIF + s->dpsi_f;
        /* e = psi_s(i) - psi_hat, psi_a = psi_f + (L_d - L_q)(i_d - j i_q) */
        e[0] = (PMSM_LD * i_dq[0] + psi_f) - psi_dq[0];
        e[1] = PMSM_LQ * i_dq[1] - psi_dq[1];
        dL = PMSM_LD - PMSM_LQ;
        pa[0] = psi_f + dL * i_dq[0];
        pa[1] = -dL * i_dq[1];
        n = pa[0] * pa[0] + pa[1] * pa[1];
        re = (e[0] * pa[0] + e[1] * pa[1]) / n;   /* Re{e / psi_a} */
        im = (pa[0] * e[1] - pa[1] * e[0]) / n;   /* Im{e / psi_a} */
        eps = -im;
        k1 = PMSM_SIGMA0 + PMSM_ZETAINF * PMSM_FABS(s->w);
        w_c = s->w + PMSM_KTHETA * eps;
        /* k_1 e + k_2 e* = 2 k_1 Re{e / psi_a} psi_a */
        coef = PMSM_R(2.0) * k1 * re;
        corr_dq[0] = coef * pa[0];
        corr_dq[1] = coef * pa[1];
        dpf = -PMSM_KF * PMSM_SQRT(n) * re;
        /* flux: exact ZOH voltage, trapezoidal R_s i, the correction held in the
           estimated frame turning at w_c: T_s sinc(w_c T_s/2) e^((theta+w_c T_s/2)J) */
        half = PMSM_R(0.5) * PMSM_OBS_T_S * w_c;
        x = half / PMSM_PI;
        sinc = x == PMSM_R(0.0) ? PMSM_R(1.0) : PMSM_SIN(PMSM_PI * x) / (PMSM_PI * x);
        pmsm_rotate(corr_dq, s->theta + half, corr);
        for (j = 0; j < 2; j++)
            psi[j] = s->psi_ab[j] + PMSM_OBS_T_S * u_ab_prev[j]
                     - (PMSM_R(0.5) * PMSM_OBS_T_S * PMSM_RS) * (s->i_prev[j] + i_ab[j])
                     + (PMSM_OBS_T_S * sinc) * corr[j];
        theta = pmsm_wrap(s->theta + PMSM_OBS_T_S * w_c);
        w = s->w + PMSM_OBS_T_S * (PMSM_KW * eps);
        dpsi_f = s->dpsi_f + PMSM_OBS_T_S * dpf;
    }
    for (j = 0; j < 2; j++) {
        s->psi_ab[j] = psi[j];
        s->i_prev[j] = i_ab[j];
    }
    s->theta = theta;
    s->w = w;
    s->dpsi_f = dpsi_f;
    s->started = 1;
    *theta_hat = theta;
    *w_hat = w;"""


def emit(observer: ReducedOrderObserver, T_s: float) -> CObserver:
    """The `CObserver` of the reduced-order observer (the gains do not depend on `T_s`).
    The current-scheduled model (`magnetic`) has no C form: `ValueError`."""
    del T_s
    if type(observer) is not ReducedOrderObserver:
        raise ValueError(f"this emitter writes ReducedOrderObserver; got "
                         f"{type(observer).__name__}.")
    if observer.magnetic is not None:
        raise ValueError("export-c writes the constant machine model only; the "
                         "reduced-order observer's current-scheduled model (`magnetic`) "
                         "has no C form. Export it with `with_magnetic(None)`.")
    m = observer.motor
    alpha_o, sigma0 = _f(observer.alpha_o), _f(observer.sigma0)
    zeta_inf, k_f = _f(observer.zeta_inf), _f(observer.k_f)
    k_theta, k_w = 2.0 * alpha_o, alpha_o ** 2
    helpers = f"""/* observer model (SI) and design */
{model_defines(m)}
#define PMSM_SIGMA0 {lit(sigma0)}
#define PMSM_ZETAINF {lit(zeta_inf)}
#define PMSM_KTHETA {lit(k_theta)}
#define PMSM_KW {lit(k_w)}
#define PMSM_KF {lit(k_f)}
"""
    title = "reduced-order flux observer with speed adaptation, Hinkkanen et al. 2018"
    doc = (
        f"Observer: reduced-order, {title}",
        "(PM-flux adaptation: Tuovinen et al., IEEE SLED 2018).",
        "M. Hinkkanen, S. E. Saarakkala, H. A. A. Awan, E. Molsa, T. Tuovinen, IEEE Trans.",
        "Ind. Appl. 54(6), 2018, doi:10.1109/TIA.2018.2858753.",
        model_doc(m),
        f"Design: alpha_o = {alpha_o!r} rad/s (k_theta = 2 alpha_o = {k_theta!r} 1/s, "
        f"k_w = alpha_o^2 = {k_w!r} 1/s^2),",
        f"  k_1 = sigma0 + zeta_inf |w| with sigma0 = {sigma0!r} 1/s, zeta_inf = "
        f"{zeta_inf!r}; k_f = {k_f!r} 1/s.",
        "Step (k >= 1), in the estimated frame at theta from psi_ab and i_(k-1):",
        "  e = L_d i_d + psi_f + j L_q i_q - psi,  psi_a = psi_f + (L_d - L_q)(i_d - j i_q)",
        "  eps = -Im{e/psi_a};  w_c = w + k_theta eps",
        "  psi   += T_s u_prev - T_s R_s (i_prev + i_k)/2",
        "           + T_s sinc(w_c T_s/2) exp((theta + w_c T_s/2) J) 2 k_1 Re{e/psi_a} psi_a",
        "  theta  = wrap(theta + T_s w_c);  w += T_s k_w eps",
        "  dpsi_f -= T_s k_f |psi_a| Re{e/psi_a}   (psi_f = model psi_f + dpsi_f)",
        "Speed output: w (the speed-adaptation state, not w_c).",
        "First sample: psi = exp(theta0 J)(L i_0 + psi_f); theta, w unchanged.",
    )
    return CObserver(name="reduced-order", title=title, doc=doc, fields=_FIELDS,
                     helpers=helpers, init=_INIT, step=_STEP)
