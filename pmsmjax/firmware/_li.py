r"""C emitter of the li-fa-leso back-EMF observers (`CLESOObserver`, `GILESOObserver`,
`FALESOObserver`: "c-leso", "gi-leso", "fa-leso") with their quadrature PLL:
`AbstractBackEMFLESO.step` line by line (`observers/_back_emf_leso.py`).

The exact ZOH discretisation is computed in C every sample in the closed form the JAX
step uses (`_li_transition`): the observer in half-size complex form
($\dot y = A_o y + g_i i + g_c\dot\lambda$, `_complex_system`), its inputs held in the
frame turning at the PLL speed, and $e^X$, $\varphi_1(X)$, $\varphi_2(X)$ of
$X = (A_o - j\hat\omega I)T_s$: as pairs of complex numbers for the C- and FA-LESO
(`phi_pair`), as the Taylor series of their action for the GI-LESO (`phi_action`); no
matrix exponential, a few hundred operations a step. The observer's matrices
`(A_s, B_s, C_s, D_x, D_1)` are read from the observer's own `_matrices(w_hat)`: each is
fitted (and checked, to rounding) as a combination of the basis functions $1$,
$\hat\omega$ and $\max(\hat\omega^2, w_c^2)$ ($w_c$ = 0 but for the GI-LESO) and made
of $2\times2$ blocks $aI + bJ$ (the complex coefficient $a + jb$), so a change of
`_matrices` within that family needs no change here; a matrix outside it is refused.
The PLL is `QuadraturePLL.step`.
"""

from __future__ import annotations

import numpy as np

from ..observers import AbstractBackEMFLESO, GILESOObserver
from . import _li_transition as tr
from ._c import CObserver, lit, model_defines, model_doc, scalar as _f


_W_FIT = np.array([-5000.0, -900.0, -80.0, -3.0, 0.0, 0.4, 60.0, 700.0, 4200.0])
_W_CHECK = np.array([-2500.0, -33.0, 1.7, 150.0, 3100.0])


def _basis(w, wc2):
    w = np.asarray(w, float)
    return np.stack([np.ones_like(w), w, np.maximum(w * w, wc2)], -1)


def _fit(values, X):
    """Least-squares coefficients `(3, m)` of the columns of `values` `(n, m)` on the
    basis `X` `(n, 3)`: each column refitted on the functions that contribute more than
    round-off (the others exactly zero: structural zeros stay zero in C), and of the
    refit, its coefficients rounded to 13 digits and (one function) the sample ratios,
    the one closest to the samples (so that -1 stays -1, not -1 + 1 ulp)."""
    coef, *_ = np.linalg.lstsq(X, values, rcond=None)
    size = np.abs(values).max(0) + 1e-300
    for col in range(values.shape[1]):
        keep = np.abs(coef[:, col]) * np.abs(X).max(0) > 1e-13 * size[col]
        coef[:, col] = 0.0
        if not keep.any():
            continue
        y, Xk = values[:, col], X[:, keep]
        sub, *_ = np.linalg.lstsq(Xk, y, rcond=None)
        cands = [sub, np.array([float(f"{c:.13g}") for c in sub])]
        if Xk.shape[1] == 1:
            cands += [np.array([y[i] / Xk[i, 0]]) for i in range(len(y)) if Xk[i, 0] != 0]
        coef[keep, col] = min(cands, key=lambda c: np.abs(Xk @ c - y).max())
    return coef


def _fit_matrices(observer, wc2):
    """`{name: coefficients (3, r, c)}` with M(w) = sum_j basis_j(w) coef_j."""
    def mats(w):
        return [np.asarray(M, float) for M in observer._matrices(np.float64(w))]

    samples = [mats(w) for w in _W_FIT]
    X = _basis(_W_FIT, wc2)
    out = {}
    for j, name in enumerate(("A", "B", "C", "Dx", "D1")):
        Y = np.stack([s[j].reshape(-1) for s in samples])
        coef = _fit(Y, X)
        shape = samples[0][j].shape
        for w in _W_CHECK:
            got = (_basis(w, wc2) @ coef).reshape(shape)
            want = mats(w)[j]
            if not np.allclose(got, want, rtol=1e-12, atol=1e-9 * (1 + np.abs(want).max())):
                raise ValueError(f"export-c: the {type(observer).__name__}'s matrix {name} "
                                 f"is not a combination of 1, w, max(w^2, w_c^2) in the "
                                 f"speed estimate; the li emitter needs updating.")
        out[name] = coef.reshape((3, *shape))
    return out


def _complex_blocks(observer, name, coef):
    """The complex coefficients `(3, r/2, c/2)` of a matrix of 2x2 blocks aI + bJ."""
    a, b = coef[:, 0::2, 0::2], coef[:, 1::2, 0::2]
    tol = 1e-12 * (1.0 + np.abs(coef).max())
    if (np.abs(coef[:, 0::2, 1::2] + b).max() > tol
            or np.abs(coef[:, 1::2, 1::2] - a).max() > tol):
        raise ValueError(f"export-c: the {type(observer).__name__}'s matrix {name} is not "
                         f"made of blocks aI + bJ; the li emitter needs updating.")
    return a + 1j * b


def _complex_system(observer, wc2):
    """The observer's complex form `(Ao (3, p, p), g_i (3, p), C (3, p - 1), Dx (3,))`
    (`AbstractBackEMFLESO._complex_system`: $A_o = [[D_x + D_1, C], [B, A]]$,
    $g_i = -[D_x + D_1; B]$, first column) as coefficients over the basis."""
    fits = _fit_matrices(observer, wc2)
    A, B, C, Dx, D1 = (_complex_blocks(observer, k, fits[k])
                       for k in ("A", "B", "C", "Dx", "D1"))
    K = Dx + D1
    Ao = np.concatenate([np.concatenate([K, C], 2), np.concatenate([B, A], 2)], 1)
    g_i = -np.concatenate([K, B], 1)[:, :, 0]
    return Ao, g_i, C[:, 0, :], Dx[:, 0, 0]


def _fit_scale(observer, wc2, p):
    """`[(c_i, e_i)]`: the observer's units of the complex state (`_complex_scale`, the
    norm the JAX step switches on) as d_i = c_i sqrt(max(w^2, w_c^2))^e_i, e_i in
    {-1, 0, 1}, checked at every fit and check speed. Any positive scaling is exact (it
    sets the number of sub-steps only); a scaling outside this family is refused."""
    ws = np.concatenate([_W_FIT, _W_CHECK])
    d = np.stack([np.asarray(observer._complex_scale(np.float64(w)), float) for w in ws])
    sb = np.sqrt(np.maximum(ws * ws, wc2))
    out = []
    for i in range(p):
        for e in (0, -1, 1):
            if e and wc2 <= 0.0:
                continue
            c = d[:, i] / sb ** e
            if np.all(np.isfinite(c)) and np.allclose(c, c[0], rtol=1e-12) and c[0] > 0:
                out.append((float(c[0]), e))
                break
        else:
            raise ValueError(f"export-c: the {type(observer).__name__}'s `_complex_scale` "
                             f"is not c sqrt(max(w^2, w_c^2))^e; the li emitter needs "
                             f"updating.")
    return out


def _x2_expr(C, Dx, s_vars, eps: str) -> str:
    """$\\hat x_2 = C s + D_x\\varepsilon_1$ as a C expression (complex)."""
    terms = [t for t in (tr.cterm(tr.entry(C[:, j]), v) for j, v in enumerate(s_vars)) if t]
    t = tr.cterm(tr.entry(Dx), eps)
    terms += [t] if t else []
    expr = terms[0] if terms else tr.ZERO
    for t in terms[1:]:
        expr = f"pmsm_cadd({expr}, {t})"
    return expr


def _pair_transition(X, gi, g_c) -> str:
    """C statements of the C-/FA-LESO's transition (`p = 2`, `_transition_c`)."""
    x = [[tr.cplx_expr(X[i][j]) for j in range(2)] for i in range(2)]
    gi0, gi1 = (tr.cterm(gi[i], "ip") or tr.ZERO for i in range(2))
    gd0, gd1 = (tr.cterm(gi[i], "delta") or tr.ZERO for i in range(2))
    return f"""        pmsm_cplx x00 = {x[0][0]}, x01 = {x[0][1]};
        pmsm_cplx x10 = {x[1][0]}, x11 = {x[1][1]};
        /* X = mu I + N with N = [[n00, x01], [x10, -n00]] traceless, N^2 = d I */
        pmsm_cplx mu = pmsm_cscale(pmsm_cadd(x00, x11), PMSM_R(0.5));
        pmsm_cplx n00 = pmsm_cscale(pmsm_csub(x00, x11), PMSM_R(0.5));
        pmsm_cplx E[3][2], g0[2], g1[2], ua[2], ub[2];
        int k;
        pmsm_phi_pair(mu, pmsm_cadd(pmsm_cmul(n00, n00), pmsm_cmul(x01, x10)), E);
        /* the inputs over the period: g0 = T_s (g_i i + g_c c), g1 = T_s^2 g_i delta */
        g0[0] = pmsm_cadd({gi0}, pmsm_cscale(c, {g_c}));
        g0[1] = {gi1};
        g1[0] = pmsm_cscale({gd0}, PMSM_OBS_T_S);
        g1[1] = pmsm_cscale({gd1}, PMSM_OBS_T_S);
        for (k = 0; k < 2; k++) {{
            ua[k] = pmsm_cadd(pmsm_cadd(pmsm_cmul(E[0][0], y[k]), pmsm_cmul(E[1][0], g0[k])),
                              pmsm_cmul(E[2][0], g1[k]));
            ub[k] = pmsm_cadd(pmsm_cadd(pmsm_cmul(E[0][1], y[k]), pmsm_cmul(E[1][1], g0[k])),
                              pmsm_cmul(E[2][1], g1[k]));
        }}
        y[0] = pmsm_cadd(ua[0], pmsm_cadd(pmsm_cmul(n00, ub[0]), pmsm_cmul(x01, ub[1])));
        y[1] = pmsm_csub(pmsm_cadd(ua[1], pmsm_cmul(x10, ub[0])), pmsm_cmul(n00, ub[1]));
        y[0] = pmsm_cmul(rot, y[0]);
        y[1] = pmsm_cmul(rot, y[1]);"""


def emit(observer: AbstractBackEMFLESO, T_s: float) -> CObserver:
    """The `CObserver` of a C-, GI- or FA-LESO at sampling period `T_s` (s; folded into
    the coefficients of $X$). The current-scheduled model (`magnetic`) has no C form:
    `ValueError`."""
    if observer.magnetic is not None:
        raise ValueError("export-c writes the constant machine model only; the li "
                         "observers' current-scheduled model (`magnetic`) has no C form. "
                         "Export it with `with_magnetic(None)`.")
    m = observer.motor
    p_ = observer.pll
    w_pll, zeta_pll, w_min = _f(p_.w_pll), _f(p_.zeta_pll), _f(p_.w_min)
    fll = _f(p_.fll)
    wc2 = _f(observer.w_c) ** 2 if isinstance(observer, GILESOObserver) else 0.0
    Ao, g_i, C, Dx = _complex_system(observer, wc2)
    n = observer.n_s
    p = 1 + n // 2
    T = float(T_s)
    # X = (A_o - j w I) T_s; g_i T_s; g_c T_s = T_s / L_q
    X = [[tr.entry(Ao[:, i, j], T, "-(wh * PMSM_OBS_T_S)" if i == j else None)
          for j in range(p)] for i in range(p)]
    gi = [tr.entry(g_i[:, i], T) for i in range(p)]
    g_c = "(PMSM_OBS_T_S / PMSM_LQ)"
    fields = (
        (f"pmsm_real s[{n}]", "internal states li-fa-leso (C-LESO: x2_hat (A/s); GI-LESO: "
                              "x2_hat, r (A s^2), q (A s); FA-LESO: z (A/s)), stationary "
                              "frame"),
        ("pmsm_real x1[2]", "estimated current x1_hat (A, stationary frame)"),
        ("pmsm_real theta", "PLL angle, wrapped to (-pi, pi] (rad)"),
        ("pmsm_real w", "PLL speed (rad/s, electrical)"),
        ("pmsm_real i_prev[2]", "current sampled at the previous instant (A)"),
        ("int started", "0 until the first sample has been seen"),
    )
    init = "\n".join(
        [f"    s->s[{j}] = PMSM_R(0.0);" for j in range(n)]
        + ["    s->x1[0] = PMSM_R(0.0);", "    s->x1[1] = PMSM_R(0.0);",
           "    s->theta = pmsm_wrap(theta0);", "    s->w = w0;",
           "    s->i_prev[0] = PMSM_R(0.0);", "    s->i_prev[1] = PMSM_R(0.0);",
           "    s->started = 0;"])
    if p == 2:
        numerics = tr.PAIR_C
        transition = _pair_transition(X, gi, g_c)
    else:
        numerics, _ = tr.degree_tables()
        transition = tr.action(X, gi, _fit_scale(observer, wc2, p), p, g_c)
    helpers = f"""/* observer model (SI) and PLL */
{model_defines(m)}
#define PMSM_WPLL {lit(w_pll)}
#define PMSM_ZPLL {lit(zeta_pll)}
#define PMSM_WMIN {lit(w_min)}
#define PMSM_FLL {lit(fll)}
#define PMSM_WC2 {lit(wc2)} /* w_c^2 of the basis max(w^2, w_c^2) (rad^2/s^2) */
/* the smallest normal number of pmsm_real (jnp.finfo(dtype).tiny) */
#define PMSM_TINY (sizeof(pmsm_real) == sizeof(float) ? (pmsm_real)FLT_MIN \\
                   : (pmsm_real)DBL_MIN)
/* sign(x) as jnp.sign: -1, 0 or +1 */
static pmsm_real pmsm_sign(pmsm_real x)
{{
    return x > PMSM_R(0.0) ? PMSM_R(1.0) : (x < PMSM_R(0.0) ? PMSM_R(-1.0) : PMSM_R(0.0));
}}

{tr.COMPLEX_C}
{numerics}"""
    s_new = [f"y[{j + 1}]" for j in range(n // 2)]
    s_old = [f"pmsm_c(s->s[{2 * j}], s->s[{2 * j + 1}])" for j in range(n // 2)]
    load = "\n".join(f"    y[{j + 1}] = {v};" for j, v in enumerate(s_old))
    store = "\n".join(f"    s->s[{2 * j}] = y[{j + 1}].re;\n    s->s[{2 * j + 1}] = "
                      f"y[{j + 1}].im;" for j in range(n // 2))
    zero = "\n".join(f"        y[{j + 1}] = pmsm_c(PMSM_R(0.0), PMSM_R(0.0));"
                     for j in range(n // 2))
    x2_new = _x2_expr(C, Dx, s_new, "pmsm_csub(y[0], ik)")
    x2_old = _x2_expr(C, Dx, s_old, "pmsm_csub(pmsm_c(s->x1[0], s->x1[1]), ip)")
    pll = _PLL.replace("@X2_OLD@", x2_old)
    step = f"""    pmsm_real wh = s->w, theta = s->theta, w = s->w;
    /* the basis of the observer's coefficients at the PLL speed */
    pmsm_real b1 = wh, b2 = wh * wh > PMSM_WC2 ? wh * wh : PMSM_WC2;
    pmsm_real half = PMSM_R(0.5) * PMSM_OBS_T_S * wh, sin_h = PMSM_SIN(half), sinc;
    pmsm_cplx ik = pmsm_c(i_ab[0], i_ab[1]), ip = pmsm_c(s->i_prev[0], s->i_prev[1]);
    pmsm_cplx dl, h, c, rot, delta, x2, y[{p}];
    pmsm_real e_hat[2];
    (void)b1;
    (void)b2;
    /* the voltage integral: exact (ZOH) voltage, trapezoidal resistive drop */
    dl = pmsm_c(PMSM_OBS_T_S * u_ab_prev[0]
                - (PMSM_R(0.5) * PMSM_OBS_T_S * PMSM_RS) * (ip.re + ik.re),
                PMSM_OBS_T_S * u_ab_prev[1]
                - (PMSM_R(0.5) * PMSM_OBS_T_S * PMSM_RS) * (ip.im + ik.im));
    /* its rate c held in the frame turning at wh, with the same integral:
       int_0^T e^(j wh t) c dt = T sinc(wh T / 2) e^(j wh T / 2) c; h = e^(j wh T / 2) */
    h = pmsm_c(PMSM_COS(half), sin_h);
    sinc = PMSM_FABS(half) < PMSM_R(1e-4) ? PMSM_R(1.0) - half * half / PMSM_R(6.0)
                                          : sin_h / half;
    c = pmsm_cmul(dl, pmsm_conj(h));
    c = pmsm_c(c.re / (PMSM_OBS_T_S * sinc), c.im / (PMSM_OBS_T_S * sinc));
    /* the current between the samples: turning at wh, linear in that frame */
    rot = pmsm_cmul(h, h);
    delta = pmsm_csub(pmsm_cmul(ik, pmsm_conj(rot)), ip);
    delta = pmsm_c(delta.re / PMSM_OBS_T_S, delta.im / PMSM_OBS_T_S);
    /* the state [x1, s] one period on (complex form, stationary frame) */
    y[0] = pmsm_c(s->x1[0], s->x1[1]);
{load}
    {{
{transition}
    }}
    if (!s->started) {{
        /* first sample: the estimated current is the measured one, no back-EMF */
{zero}
        y[0] = ik;
    }}
    /* e_hat = -L_q x2_hat, x2_hat = C s + D_x (x1 - i_k) */
    x2 = {x2_new};
    e_hat[0] = -PMSM_LQ * x2.re;
    e_hat[1] = -PMSM_LQ * x2.im;
{pll}
{store}
    s->x1[0] = y[0].re;
    s->x1[1] = y[0].im;
    s->i_prev[0] = i_ab[0];
    s->i_prev[1] = i_ab[1];
    s->theta = theta;
    s->w = w;
    s->started = 1;
    *theta_hat = theta;
    *w_hat = w;"""
    name = {"CLESOObserver": "c-leso", "GILESOObserver": "gi-leso",
            "FALESOObserver": "fa-leso"}[type(observer).__name__]
    title = f"{name} back-EMF observer of li-fa-leso with a quadrature PLL"
    form = ("e^X, phi_1(X), phi_2(X) of the 2x2 complex X as pairs of complex numbers"
            if p == 2 else
            f"the Taylor series of the action of e^X, phi_1, phi_2 of the {p}x{p} complex X")
    doc = (
        f"Observer: {title}.",
        model_doc(m),
        f"Design: {', '.join(f'{k} = {_f(v)!r}' for k, v in observer._own_design().items())};",
        f"PLL: w_pll = {w_pll!r} rad/s, zeta_pll = {zeta_pll!r}, w_min = {w_min!r} rad/s.",
        "Step: the exact ZOH transition over T_s of the observer driven by the current",
        "turning at the PLL speed (linear in that frame) and the voltage integral, in",
        "complex form with X = (A_o - j w I) T_s:",
        f"  {form};",
        "then e_hat = -L_q (C s + D_x (x1 - i_k)) and the PLL at theta + T_s w:",
        "eps = -(e_hat . [cos, sin]) w / (psi_ex max(w^2, w_min^2)),",
        "theta = wrap(theta + T_s w + T_s k_p eps), w += T_s k_i eps, plus the",
        "low-speed detector term and the gated FLL assist of QuadraturePLL.step.",
        "First sample: x1 = i_0, s = 0; theta, w unchanged.",
    )
    return CObserver(name=name, title=title, doc=doc, fields=fields, helpers=helpers,
                     init=init, step=step)


_PLL = """    if (s->started) {
        /* quadrature PLL at the predicted angle */
        pmsm_real k_p = PMSM_R(2.0) * PMSM_ZPLL * PMSM_WPLL, k_i = PMSM_WPLL * PMSM_WPLL;
        pmsm_real th_p = s->theta + PMSM_OBS_T_S * s->w;
        pmsm_real cp = PMSM_COS(th_p), sp = PMSM_SIN(th_p);
        pmsm_real i_d = cp * i_ab[0] + sp * i_ab[1];
        pmsm_real psi_ex = PMSM_PSIF + (PMSM_LD - PMSM_LQ) * i_d;
        pmsm_real e_perp = -(e_hat[0] * cp + e_hat[1] * sp);
        pmsm_real psi = PMSM_FABS(psi_ex) > PMSM_R(1e-12) ? psi_ex : PMSM_R(1e-12);
        pmsm_real w2 = s->w * s->w > PMSM_WMIN * PMSM_WMIN ? s->w * s->w
                                                              : PMSM_WMIN * PMSM_WMIN;
        pmsm_real e_q = -e_hat[0] * sp + e_hat[1] * cp;
        pmsm_real fade = PMSM_R(1.0) - PMSM_FABS(s->w) / PMSM_WMIN;
        pmsm_real e_pll, e_prev[2], cross, dot, n2p, n2, w_e, prod, mg, g, sgn, adot, tiny;
        pmsm_cplx x2p;
        if (fade < PMSM_R(0.0)) fade = PMSM_R(0.0);
        /* below w_min: the sign of the back-EMF's q component where it disagrees with
           the speed estimate's */
        e_pll = e_perp * s->w / (psi * w2)
                + e_perp * fade * (pmsm_sign(e_q) - pmsm_sign(s->w)) / (psi * PMSM_WMIN);
        w = s->w + PMSM_OBS_T_S * k_i * e_pll;
        /* frequency-locked-loop assist: the back-EMF's rotation since the last sample,
           gated off near lock, the gate's direction from the speed estimate */
        x2p = @X2_OLD@;
        e_prev[0] = -PMSM_LQ * x2p.re;
        e_prev[1] = -PMSM_LQ * x2p.im;
        cross = e_prev[0] * e_hat[1] - e_prev[1] * e_hat[0];
        dot = e_prev[0] * e_hat[0] + e_prev[1] * e_hat[1];
        n2p = e_prev[0] * e_prev[0] + e_prev[1] * e_prev[1];
        n2 = e_hat[0] * e_hat[0] + e_hat[1] * e_hat[1];
        tiny = PMSM_TINY;
        sgn = dot < PMSM_R(0.0) ? PMSM_R(-1.0) : PMSM_R(1.0);
        adot = PMSM_FABS(dot);
        w_e = PMSM_ATAN2(sgn * cross, (cross == PMSM_R(0.0) && adot == PMSM_R(0.0))
                         ? PMSM_R(1.0) : adot) / PMSM_OBS_T_S;
        prod = PMSM_SQRT(n2p * n2 + tiny);
        mg = prod / (prod + (psi_ex * PMSM_WMIN) * (psi_ex * PMSM_WMIN));
        g = PMSM_R(0.5) * mg * (PMSM_R(1.0) - PMSM_TANH(s->w / PMSM_WMIN) * e_q
                                / PMSM_SQRT(n2 + tiny));
        w += (PMSM_OBS_T_S * PMSM_FLL * PMSM_WPLL) * g * (w_e - s->w);
        theta = pmsm_wrap(th_p + PMSM_OBS_T_S * k_p * e_pll);
    }"""
