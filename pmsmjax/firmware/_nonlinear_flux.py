r"""C emitter of the nonlinear (gradient) flux observer of Lee2010/Ortega2011 with its PLL
(`NonlinearFluxObserver`, "nonlinear-flux"): `NonlinearFluxObserver.step` line by line
(`observers/_nonlinear_flux.py`), every variant.

Per step (k >= 1): the flux integrates the held voltage exactly and the measured
resistive drop by the trapezoid; the gradient term from $\eta_{k-1}$ (target from
$i_{k-1}$ in the frame $\hat\theta_{k-1}$), held in the frame turning at
$\hat\omega_{k-1}$ (sinc rule), its factor floored at $-1/(2T_s)$; the PM-flux estimate
by forward Euler (`"adaptive"`); the limit of $|\eta_k|$ (`"limited"`); the PLL at the
predicted angle $\hat\theta_{k-1} + T_s\hat\omega_{k-1}$.
"""

from __future__ import annotations

from ..observers import NonlinearFluxObserver
from ._c import CObserver, lit, model_defines, model_doc, scalar as _f


_FIELDS = (
    ("pmsm_real psi_ab[2]", "estimated stator flux, stationary frame (V s)"),
    ("pmsm_real theta", "PLL angle, wrapped to (-pi, pi] (rad)"),
    ("pmsm_real w", "PLL speed (rad/s)"),
    ("pmsm_real psi_f", "PM-flux estimate (V s; the model's unless adaptive)"),
    ("pmsm_real i_prev[2]", "current sampled at the previous instant (A, alpha-beta)"),
    ("int started", "0 until the first sample has been seen"),
)

_INIT = """    s->psi_ab[0] = PMSM_R(0.0);
    s->psi_ab[1] = PMSM_R(0.0);
    s->theta = pmsm_wrap(theta0);
    s->w = w0;
    s->psi_f = PMSM_PSIF;
    s->i_prev[0] = PMSM_R(0.0);
    s->i_prev[1] = PMSM_R(0.0);
    s->started = 0;"""


def emit(observer: NonlinearFluxObserver, T_s: float) -> CObserver:
    """The `CObserver` of the nonlinear flux observer at sampling period `T_s` (s: the
    floor of the gradient factor, -1/(2 T_s), is compiled in)."""
    m = observer.motor
    variant = observer.variant
    lam, w_pll, zeta, k_psi = (_f(observer.lam), _f(observer.w_pll), _f(observer.zeta_pll),
                               _f(observer.k_psi))
    psi_f = _f(m.psi_f)
    gamma = lam / psi_f ** 2
    kappa = 0.5 * k_psi / psi_f ** 2
    k_p, k_i = 2.0 * zeta * w_pll, w_pll ** 2
    adaptive = variant == "adaptive"
    if variant == "limited":
        factor = "q = PMSM_R(0.0); /* no gradient term */\n        (void)g;"
    elif variant == "clamped":
        factor = "q = PMSM_HALF_GAMMA * (g > PMSM_R(0.0) ? g : PMSM_R(0.0));"
    else:
        factor = "q = PMSM_HALF_GAMMA * g;"
    psi_f_rate = ("psi_f = s->psi_f + PMSM_OBS_T_S * ((-PMSM_KAPPA * ref0) * g);"
                  if adaptive else "psi_f = s->psi_f;")
    base0 = "s->psi_f" if adaptive else "PMSM_PSIF"
    limit = """
        /* the magnitude limit: eta scaled back onto the circle where it is outside */
        n = PMSM_SQRT(eta[0] * eta[0] + eta[1] * eta[1]);
        a = PMSM_FABS(ref1);
        if (n > a) {
            for (j = 0; j < 2; j++) {
                eta[j] = eta[j] * (a / n);
                x[j] = PMSM_LQ * i_ab[j] + eta[j];
            }
        }""" if variant == "limited" else ""
    helpers = f"""/* observer model and design (SI) */
{model_defines(m)}
#define PMSM_HALF_GAMMA {lit(0.5 * gamma)}
#define PMSM_KAPPA {lit(kappa)}
#define PMSM_KP {lit(k_p)}
#define PMSM_KI {lit(k_i)}
#define PMSM_Q_MIN {lit(-0.5 / T_s)}
"""
    step = f"""    pmsm_real x[2], eta[2], theta, w, psi_f, c, sn;
    int j;
    if (!s->started) {{
        /* first sample: the flux at the initial angle, nothing else moves */
        pmsm_real ref_i;
        c = PMSM_COS(s->theta);
        sn = PMSM_SIN(s->theta);
        ref_i = {base0} + (PMSM_LD - PMSM_LQ) * (i_ab[0] * c + i_ab[1] * sn);
        x[0] = PMSM_LQ * i_ab[0] + ref_i * c;
        x[1] = PMSM_LQ * i_ab[1] + ref_i * sn;
        theta = s->theta;
        w = s->w;
        psi_f = s->psi_f;
    }} else {{
        pmsm_real eta0[2], ref0, ref1, g, q, half, xs, sinc, rot[2], th_p, eps, n, a;
        (void)n;
        (void)a;
        /* the gradient term at t_(k-1), held in the frame turning at w over the period */
        c = PMSM_COS(s->theta);
        sn = PMSM_SIN(s->theta);
        ref0 = {base0} + (PMSM_LD - PMSM_LQ) * (s->i_prev[0] * c + s->i_prev[1] * sn);
        for (j = 0; j < 2; j++)
            eta0[j] = s->psi_ab[j] - PMSM_LQ * s->i_prev[j];
        g = ref0 * ref0 - (eta0[0] * eta0[0] + eta0[1] * eta0[1]);
        {factor}
        if (q < PMSM_Q_MIN) q = PMSM_Q_MIN;
        half = PMSM_R(0.5) * PMSM_OBS_T_S * s->w;
        xs = half / PMSM_PI;
        sinc = xs == PMSM_R(0.0) ? PMSM_R(1.0) : PMSM_SIN(PMSM_PI * xs) / (PMSM_PI * xs);
        pmsm_rotate(eta0, half, rot);
        for (j = 0; j < 2; j++)
            x[j] = s->psi_ab[j] + PMSM_OBS_T_S * u_ab_prev[j]
                   - (PMSM_R(0.5) * PMSM_OBS_T_S * PMSM_RS) * (s->i_prev[j] + i_ab[j])
                   + ((PMSM_OBS_T_S * sinc) * q) * rot[j];
        {psi_f_rate}
        /* the PLL's predicted angle and the model's target at t_k in its frame */
        th_p = s->theta + PMSM_OBS_T_S * s->w;
        c = PMSM_COS(th_p);
        sn = PMSM_SIN(th_p);
        ref1 = PMSM_PSIF + (PMSM_LD - PMSM_LQ) * (i_ab[0] * c + i_ab[1] * sn);
        for (j = 0; j < 2; j++)
            eta[j] = x[j] - PMSM_LQ * i_ab[j];{limit}
        eps = (c * eta[1] - sn * eta[0]) / ref1;
        theta = pmsm_wrap(th_p + (PMSM_OBS_T_S * PMSM_KP) * eps);
        w = s->w + (PMSM_OBS_T_S * PMSM_KI) * eps;
    }}
    for (j = 0; j < 2; j++) {{
        s->psi_ab[j] = x[j];
        s->i_prev[j] = i_ab[j];
    }}
    s->theta = theta;
    s->w = w;
    s->psi_f = psi_f;
    s->started = 1;
    *theta_hat = theta;
    *w_hat = w;"""
    title = ("nonlinear (gradient) flux observer with a PLL, Lee et al. 2010 / Ortega et "
             "al. 2011")
    term = {"gradient": "q = (gamma/2) (ref0^2 - |eta0|^2)",
            "clamped": "q = (gamma/2) max(ref0^2 - |eta0|^2, 0)",
            "adaptive": "q = (gamma/2) (ref0^2 - |eta0|^2), ref0 with psi_f_hat",
            "limited": "q = 0 (pure integrator), then |eta_k| limited to ref1"}[variant]
    doc = (
        f"Observer: nonlinear-flux ({variant}), {title}.",
        "J. Lee et al., IEEE Trans. Power Electron. 25(2), 290-297, 2010; R. Ortega et al.,",
        "IEEE Trans. Control Syst. Technol. 19(3), 601-614, 2011.",
        model_doc(m),
        f"Design: lam = {lam!r} 1/s (gamma = lam/psi_f^2 = {gamma!r} 1/(V^2 s^3)),",
        f"  w_pll = {w_pll!r} rad/s, zeta_pll = {zeta!r} (k_p = {k_p!r}, k_i = {k_i!r}),",
        f"  k_psi = {k_psi!r} 1/s (kappa = {kappa!r}; variant 'adaptive' only).",
        "eta = psi - L_q i; ref = psi_f + (L_d - L_q) i_d (i_d in the PLL's frame;",
        "  psi_f_hat in ref0 if adaptive, the model's psi_f in ref1).",
        "Step (k >= 1), eta0 = psi - L_q i_prev, ref0 at theta:",
        f"  {term}, floored at -1/(2 T_s)",
        "  psi  += T_s u_prev - T_s R_s (i_prev + i_k)/2 + T_s sinc(w T_s/2) q e^(w T_s/2 J) eta0",
        "  th_p  = theta + T_s w; eps = (eta_k x [cos th_p, sin th_p]) / ref1",
        "  theta = wrap(th_p + T_s k_p eps); w += T_s k_i eps",
        "First sample: psi = L_q i_0 + ref e^(theta0 J)[1,0]; theta, w unchanged.",
    )
    return CObserver(name="nonlinear-flux", title=title, doc=doc, fields=_FIELDS,
                     helpers=helpers, init=_INIT, step=step)
