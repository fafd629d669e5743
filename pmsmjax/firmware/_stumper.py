r"""C emitter of stumper's parallel-model estimator (`ParallelModelObserver`,
"parallel-model"): `ParallelModelObserver.step` line by line
(`observers/_parallel_model.py`): the current in polar form (5)-(6), its filtered rates,
the back-EMF along and across the current (13)-(14) at the interval's midpoint angle, the
raw angle (16)-(17) (corrected) and speed (18)-(19) from the chord of the back-EMF, the
tracking filter and the speed low-pass (forward Euler).
"""

from __future__ import annotations

from ..observers._parallel_model import E_MIN, RHO_MIN, ParallelModelObserver
from ._c import CObserver, lit, model_defines, model_values, scalar as _f


_FIELDS = (
    ("pmsm_real rho_prev", "current magnitude at the previous instant (A)"),
    ("pmsm_real phi_prev", "current angle at the previous instant (rad)"),
    ("pmsm_real rho_dot", "filtered rate of the current magnitude (A/s)"),
    ("pmsm_real phi_dot", "filtered rate of the current angle (rad/s)"),
    ("pmsm_real theta", "estimated electrical angle, wrapped to (-pi, pi] (rad)"),
    ("pmsm_real z", "tracking filter's speed state (rad/s)"),
    ("pmsm_real w", "low-passed speed estimate (rad/s)"),
    ("int started", "0 until the first sample has been seen"),
)

_INIT = """    s->rho_prev = PMSM_R(0.0);
    s->phi_prev = PMSM_R(0.0);
    s->rho_dot = PMSM_R(0.0);
    s->phi_dot = w0;
    s->theta = pmsm_wrap(theta0);
    s->z = w0;
    s->w = w0;
    s->started = 0;"""


def emit(observer: ParallelModelObserver, T_s: float) -> CObserver:
    m = observer.motor
    R_s, L_d, L_q, psi_f = model_values(m)
    v1, v2, T_LP, T_w = (_f(observer.v1), _f(observer.v2), _f(observer.T_LP),
                         _f(observer.T_w))
    if not T_s < 2.0 * min(T_LP, T_w):
        raise ValueError(f"`export_c(T_s=...)` must be below 2 min(T_LP, T_w) = "
                         f"{2.0 * min(T_LP, T_w)!r} s for the parallel-model observer "
                         f"(forward-Euler filters); got {T_s!r}.")
    helpers = f"""/* observer model and design (SI) */
{model_defines(m)}
#define PMSM_V1 {lit(v1)}
#define PMSM_V2 {lit(v2)}
#define PMSM_TLP {lit(T_LP)}
#define PMSM_TW {lit(T_w)}
#define PMSM_RHO_MIN {lit(RHO_MIN)}
#define PMSM_E_MIN {lit(E_MIN)}
"""
    step = """    pmsm_real i_a = i_ab[0], i_b = i_ab[1];
    pmsm_real rho, phi, d_rho, h, rho_m, phi_m, c, rho_dot, phi_dot, im0, im1, sg, pred;
    pmsm_real phi_dot_chord, cp, sp, u_P, u_O, e_P, e_O, y, x, ang, theta_raw, e_mag;
    pmsm_real i_d_hat, K_ext, arg, w_raw, eps, z, theta, w;
    int ok;
    /* (5)-(6): polar form; the angle is held below RHO_MIN */
    if (i_a * i_a + i_b * i_b > PMSM_RHO_MIN * PMSM_RHO_MIN) {
        rho = PMSM_SQRT(i_a * i_a + i_b * i_b);
        phi = PMSM_ATAN2(i_b, i_a);
    } else {
        rho = PMSM_R(0.0);
        phi = s->phi_prev;
    }
    d_rho = rho - s->rho_prev;
    h = PMSM_R(0.5) * pmsm_wrap(phi - s->phi_prev);
    rho_m = PMSM_R(0.5) * (rho + s->rho_prev);
    phi_m = s->phi_prev + h;
    c = PMSM_OBS_T_S / PMSM_TLP;
    rho_dot = s->rho_dot + c * (d_rho / PMSM_OBS_T_S - s->rho_dot);
    phi_dot = s->phi_dot + c * (PMSM_R(2.0) * h / PMSM_OBS_T_S - s->phi_dot);
    im0 = rho_m * PMSM_COS(h);                 /* trapezoidal mean current, frame phi_m */
    im1 = PMSM_R(0.5) * d_rho * PMSM_SIN(h);
    sg = s->z >= PMSM_R(0.0) ? PMSM_R(1.0) : PMSM_R(-1.0);
    pred = s->theta + PMSM_R(0.5) * PMSM_OBS_T_S * s->z;
    phi_dot_chord = (PMSM_R(2.0) / PMSM_OBS_T_S) * PMSM_SIN(PMSM_R(0.5) * PMSM_OBS_T_S
                                                            * phi_dot);
    /* (11)-(14) at phi_m, with the chord rates and the mean current's resistive drop */
    cp = PMSM_COS(phi_m);
    sp = PMSM_SIN(phi_m);
    u_P = u_ab_prev[0] * cp + u_ab_prev[1] * sp;
    u_O = u_ab_prev[0] * sp - u_ab_prev[1] * cp;
    e_P = u_P - PMSM_RS * rho_m - PMSM_LQ * (rho_dot * PMSM_COS(h));
    e_O = -u_O - PMSM_LQ * rho_m * phi_dot_chord;
    e_P = e_P + PMSM_RS * (rho_m - im0);
    e_O = e_O - PMSM_RS * im1;
    /* (16)-(17) corrected: theta_raw = phi_m + atan2(-s e_P, s e_O) */
    y = -sg * e_P;
    x = sg * e_O;
    ok = x * x + y * y > PMSM_E_MIN * PMSM_E_MIN;
    ang = ok ? PMSM_ATAN2(y, x) : pred - phi_m;
    theta_raw = phi_m + ang;
    e_mag = ok ? PMSM_SQRT(e_P * e_P + e_O * e_O) : PMSM_R(0.0);
    /* (18)-(19): |chord| = 2 K sin(w T_s/2)/T_s, K the extended flux */
    i_d_hat = rho_m * PMSM_COS(phi_m - theta_raw);
    K_ext = PMSM_PSIF + (PMSM_LD - PMSM_LQ) * i_d_hat;
    arg = PMSM_R(0.5) * PMSM_OBS_T_S * e_mag / K_ext;
    arg = arg < PMSM_R(0.0) ? PMSM_R(0.0) : (arg > PMSM_R(0.99) ? PMSM_R(0.99) : arg);
    w_raw = sg * (PMSM_R(2.0) / PMSM_OBS_T_S) * PMSM_ASIN(arg);
    /* tracking filter and speed low-pass (forward Euler) */
    eps = pmsm_wrap(theta_raw - pred);
    z = s->z + PMSM_OBS_T_S * PMSM_V1 * eps;
    theta = pmsm_wrap(s->theta + PMSM_OBS_T_S * (s->z + PMSM_V2 * eps));
    w = s->w + (PMSM_OBS_T_S / PMSM_TW) * (w_raw - s->w);
    s->rho_prev = rho;
    s->phi_prev = phi;
    if (s->started) {
        s->rho_dot = rho_dot;
        s->phi_dot = phi_dot;
        s->theta = theta;
        s->z = z;
        s->w = w;
    }
    s->started = 1;
    *theta_hat = s->theta;
    *w_hat = s->w;"""
    title = "parallel-model estimator, stumper (5)-(19) with a tracking filter"
    doc = (
        f"Observer: parallel-model, {title}.",
        f"Model: R_s = {R_s!r} Ohm, L = L_q = {L_q!r} H (L_d = {L_d!r} H for the extended",
        f"flux), psi_f = {psi_f!r} V s. Design: v1 = {v1!r} 1/s^2, v2 = {v2!r} 1/s,",
        f"T_LP = {T_LP!r} s, T_w = {T_w!r} s.",
        "Step: current polar (rho, phi); midpoint phi_m of the interval; filtered rates",
        "rho_dot, phi_dot (forward Euler, T_LP); back-EMF e_P, e_O along/across the",
        "current at phi_m; theta_raw = phi_m + atan2(-s e_P, s e_O), s = sign(z);",
        "w_raw = s (2/T_s) asin(clip(T_s |e|/(2 K_ext), 0, 0.99));",
        "eps = wrap(theta_raw - theta - T_s z/2); z += T_s v1 eps;",
        "theta = wrap(theta + T_s (z_old + v2 eps)); w += (T_s/T_w)(w_raw - w).",
        "First sample: only rho_prev, phi_prev are taken; the estimate is unchanged.",
    )
    return CObserver(name="parallel-model", title=title, doc=doc, fields=_FIELDS,
                     helpers=helpers, init=_INIT, step=step)
