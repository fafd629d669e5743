r"""C emitter of the li-fa-leso back-EMF observers (`CLESOObserver`, `GILESOObserver`,
`FALESOObserver`: "c-leso", "gi-leso", "fa-leso") with their quadrature PLL:
`AbstractBackEMFLESO.step` line by line (`observers/_back_emf_leso.py`).

The exact ZOH discretisation is computed in C every sample as the exponential of the
real augmented system at the PLL speed (the matrix whose transition `_propagator`
returns), by a balanced scaling-and-squaring Taylor series (4 balancing sweeps, degree
12, 6 squarings); the Python step computes the same transition in the half-size complex
form (`_transition`), so the two agree to round-off. The observer's matrices
`(A_s, B_s, C_s, D_x, D_1)` are read from the observer's own `_matrices(w_hat)`: each
is fitted (and checked, to rounding) as a combination of the basis functions $1$, $\hat\omega$ and
$\max(\hat\omega^2, w_c^2)$ ($w_c$ = 0 but for the GI-LESO), so a change of
`_matrices` within that family needs no change here; a matrix outside it is refused.
The PLL is `QuadraturePLL.step`.
"""

from __future__ import annotations

import numpy as np

from ..observers import AbstractBackEMFLESO, GILESOObserver
from ._c import CObserver, lit, model_defines, model_doc, scalar as _f


_W_FIT = np.array([-5000.0, -900.0, -80.0, -3.0, 0.0, 0.4, 60.0, 700.0, 4200.0])
_W_CHECK = np.array([-2500.0, -33.0, 1.7, 150.0, 3100.0])


def _basis(w, wc2):
    w = np.asarray(w, float)
    return np.stack([np.ones_like(w), w, np.maximum(w * w, wc2)], -1)


def _fit_matrices(observer, wc2):
    """`[(name, coefficients (3, r, c))]` with M(w) = sum_j basis_j(w) coef_j."""
    def mats(w):
        return [np.asarray(M, float) for M in observer._matrices(np.float64(w))]

    samples = [mats(w) for w in _W_FIT]
    X = _basis(_W_FIT, wc2)
    out = []
    for j, name in enumerate(("A", "B", "C", "Dx", "D1")):
        Y = np.stack([s[j].reshape(-1) for s in samples])
        coef, *_ = np.linalg.lstsq(X, Y, rcond=None)
        coef[np.abs(coef) < 1e-300] = 0.0
        shape = samples[0][j].shape
        for w in _W_CHECK:
            got = (_basis(w, wc2) @ coef).reshape(shape)
            want = mats(w)[j]
            if not np.allclose(got, want, rtol=1e-12, atol=1e-9 * (1 + np.abs(want).max())):
                raise ValueError(f"export-c: the {type(observer).__name__}'s matrix {name} "
                                 f"is not a combination of 1, w, max(w^2, w_c^2) in the "
                                 f"speed estimate; the li emitter needs updating.")
        out.append((name, coef.reshape((3, *shape))))
    return out


def _mat_c(name, coef) -> list[str]:
    """C statements filling `name[r][c]` from the basis values b0, b1, b2."""
    _, r, c = coef.shape
    lines = []
    for i in range(r):
        for j in range(c):
            terms = [f"{lit(coef[k, i, j])} * b{k}" for k in range(3) if coef[k, i, j] != 0]
            lines.append(f"    {name}[{i}][{j}] = {' + '.join(terms) if terms else 'PMSM_R(0.0)'};")
    return lines


def emit(observer: AbstractBackEMFLESO, T_s: float) -> CObserver:
    """The `CObserver` of a C-, GI- or FA-LESO (the ZOH matrices are computed in C at
    `PMSM_OBS_T_S`)."""
    del T_s
    m = observer.motor
    p = observer.pll
    w_pll, zeta_pll, w_min = _f(p.w_pll), _f(p.zeta_pll), _f(p.w_min)
    fll = _f(p.fll)
    wc2 = _f(observer.w_c) ** 2 if isinstance(observer, GILESOObserver) else 0.0
    fits = _fit_matrices(observer, wc2)
    n = observer.n_s
    N = n + 8
    ii, dd, cc = n + 2, n + 4, n + 6
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
    shapes = {name: coef.shape[1:] for name, coef in fits}
    mat_decl = "".join(f"    pmsm_real {name}[{r}][{c}];\n" for name, (r, c) in shapes.items())
    mat_fill = "\n".join(line for name, coef in fits for line in _mat_c(name, coef))
    helpers = f"""/* observer model (SI) and PLL */
{model_defines(m)}
#define PMSM_WPLL {lit(w_pll)}
#define PMSM_ZPLL {lit(zeta_pll)}
#define PMSM_WMIN {lit(w_min)}
#define PMSM_FLL {lit(fll)}
/* the smallest normal number of pmsm_real (jnp.finfo(dtype).tiny) */
#define PMSM_TINY (sizeof(pmsm_real) == sizeof(float) ? (pmsm_real)FLT_MIN \\
                   : (pmsm_real)DBL_MIN)
/* sign(x) as jnp.sign: -1, 0 or +1 */
static pmsm_real pmsm_sign(pmsm_real x)
{{
    return x > PMSM_R(0.0) ? PMSM_R(1.0) : (x < PMSM_R(0.0) ? PMSM_R(-1.0) : PMSM_R(0.0));
}}
#define PMSM_N {N}   /* augmented state [x1, s, i, delta, c] */
#define PMSM_NS {n}

/* the observer's matrices at speed w: basis 1, w, max(w^2, w_c^2) */
static void pmsm_matrices(pmsm_real w, pmsm_real A[{n}][{n}], pmsm_real B[{n}][2],
                          pmsm_real C[2][{n}], pmsm_real Dx[2][2], pmsm_real D1[2][2])
{{
    pmsm_real b0 = PMSM_R(1.0), b1 = w;
    pmsm_real b2 = w * w > {lit(wc2)} ? w * w : {lit(wc2)};
    (void)b0;
    (void)b1;
    (void)b2;
{mat_fill}
}}

static void pmsm_matmul(pmsm_real X[PMSM_N][PMSM_N], pmsm_real Y[PMSM_N][PMSM_N],
                        pmsm_real Z[PMSM_N][PMSM_N])
{{
    int i, j, k;
    for (i = 0; i < PMSM_N; i++)
        for (j = 0; j < PMSM_N; j++) {{
            pmsm_real acc = PMSM_R(0.0);
            for (k = 0; k < PMSM_N; k++) acc += X[i][k] * Y[k][j];
            Z[i][j] = acc;
        }}
}}

/* expm(M) in place: balancing (4 sweeps), Taylor degree 12 of M/2^6, 6 squarings */
static void pmsm_expm(pmsm_real M[PMSM_N][PMSM_N])
{{
    pmsm_real d[PMSM_N], E[PMSM_N][PMSM_N], T[PMSM_N][PMSM_N], W[PMSM_N][PMSM_N];
    pmsm_real r[PMSM_N], c[PMSM_N];
    int i, j, k, sweep;
    for (i = 0; i < PMSM_N; i++) d[i] = PMSM_R(1.0);
    for (sweep = 0; sweep < 4; sweep++) {{
        for (i = 0; i < PMSM_N; i++) {{ r[i] = PMSM_R(0.0); c[i] = PMSM_R(0.0); }}
        for (i = 0; i < PMSM_N; i++)
            for (j = 0; j < PMSM_N; j++)
                if (i != j) {{
                    pmsm_real v = PMSM_FABS(M[i][j]) * d[j] / d[i];
                    r[i] += v;
                    c[j] += v;
                }}
        for (i = 0; i < PMSM_N; i++)
            if (r[i] > PMSM_R(0.0) && c[i] > PMSM_R(0.0)) d[i] *= PMSM_SQRT(r[i] / c[i]);
    }}
    for (i = 0; i < PMSM_N; i++)
        for (j = 0; j < PMSM_N; j++) {{
            M[i][j] = (M[i][j] * d[j] / d[i]) / PMSM_R(64.0);
            E[i][j] = T[i][j] = (i == j) ? PMSM_R(1.0) : PMSM_R(0.0);
        }}
    for (k = 1; k <= 12; k++) {{
        pmsm_matmul(T, M, W);
        for (i = 0; i < PMSM_N; i++)
            for (j = 0; j < PMSM_N; j++) {{
                T[i][j] = W[i][j] / (pmsm_real)k;
                E[i][j] += T[i][j];
            }}
    }}
    for (k = 0; k < 6; k++) {{
        pmsm_matmul(E, E, W);
        for (i = 0; i < PMSM_N; i++)
            for (j = 0; j < PMSM_N; j++) E[i][j] = W[i][j];
    }}
    for (i = 0; i < PMSM_N; i++)
        for (j = 0; j < PMSM_N; j++) M[i][j] = E[i][j] * d[i] / d[j];
}}
"""
    step = f"""{mat_decl}    pmsm_real M[PMSM_N][PMSM_N], v[PMSM_N], x1[2], sn[PMSM_NS], \
eps[2], e_hat[2];
    pmsm_real d_lam[2], half, x, sinc, cvec[2], delta[2], tmp[2], wh = s->w;
    pmsm_real theta = s->theta, w = s->w;
    int i, j;
    pmsm_matrices(wh, A, B, C, Dx, D1);
    /* the augmented matrix of _propagator, times T_s */
    for (i = 0; i < PMSM_N; i++)
        for (j = 0; j < PMSM_N; j++) M[i][j] = PMSM_R(0.0);
    for (i = 0; i < 2; i++) {{
        for (j = 0; j < 2; j++) {{
            M[i][j] = Dx[i][j] + D1[i][j];
            M[i][{ii} + j] = -(Dx[i][j] + D1[i][j]);
        }}
        for (j = 0; j < PMSM_NS; j++) M[i][2 + j] = C[i][j];
        M[i][{cc} + i] = PMSM_R(1.0) / PMSM_LQ;
    }}
    for (i = 0; i < PMSM_NS; i++) {{
        for (j = 0; j < 2; j++) {{
            M[2 + i][j] = B[i][j];
            M[2 + i][{ii} + j] = -B[i][j];
        }}
        for (j = 0; j < PMSM_NS; j++) M[2 + i][2 + j] = A[i][j];
    }}
    /* i, delta, c blocks: w_hat J; d i/dt includes delta */
    M[{ii}][{ii} + 1] = -wh; M[{ii} + 1][{ii}] = wh;
    M[{ii}][{dd}] = PMSM_R(1.0); M[{ii} + 1][{dd} + 1] = PMSM_R(1.0);
    M[{dd}][{dd} + 1] = -wh; M[{dd} + 1][{dd}] = wh;
    M[{cc}][{cc} + 1] = -wh; M[{cc} + 1][{cc}] = wh;
    for (i = 0; i < PMSM_N; i++)
        for (j = 0; j < PMSM_N; j++) M[i][j] *= PMSM_OBS_T_S;
    pmsm_expm(M);
    for (j = 0; j < 2; j++)
        d_lam[j] = PMSM_OBS_T_S * u_ab_prev[j]
                   - (PMSM_R(0.5) * PMSM_OBS_T_S * PMSM_RS) * (s->i_prev[j] + i_ab[j]);
    half = PMSM_R(0.5) * PMSM_OBS_T_S * wh;
    x = half / PMSM_PI;
    sinc = x == PMSM_R(0.0) ? PMSM_R(1.0) : PMSM_SIN(PMSM_PI * x) / (PMSM_PI * x);
    pmsm_rotate(d_lam, -half, tmp);
    cvec[0] = tmp[0] / (PMSM_OBS_T_S * sinc);
    cvec[1] = tmp[1] / (PMSM_OBS_T_S * sinc);
    pmsm_rotate(i_ab, PMSM_R(-2.0) * half, tmp);
    delta[0] = (tmp[0] - s->i_prev[0]) / PMSM_OBS_T_S;
    delta[1] = (tmp[1] - s->i_prev[1]) / PMSM_OBS_T_S;
    v[0] = s->x1[0]; v[1] = s->x1[1];
    for (j = 0; j < PMSM_NS; j++) v[2 + j] = s->s[j];
    v[{ii}] = s->i_prev[0]; v[{ii} + 1] = s->i_prev[1];
    v[{dd}] = delta[0]; v[{dd} + 1] = delta[1];
    v[{cc}] = cvec[0]; v[{cc} + 1] = cvec[1];
    for (i = 0; i < 2 + PMSM_NS; i++) {{
        pmsm_real acc = PMSM_R(0.0);
        for (j = 0; j < PMSM_N; j++) acc += M[i][j] * v[j];
        if (i < 2) x1[i] = acc; else sn[i - 2] = acc;
    }}
    if (!s->started) {{
        /* first sample: the estimated current is the measured one, no back-EMF */
        for (j = 0; j < PMSM_NS; j++) sn[j] = PMSM_R(0.0);
        x1[0] = i_ab[0];
        x1[1] = i_ab[1];
    }}
    eps[0] = x1[0] - i_ab[0];
    eps[1] = x1[1] - i_ab[1];
    for (i = 0; i < 2; i++) {{
        pmsm_real acc = Dx[i][0] * eps[0] + Dx[i][1] * eps[1];
        for (j = 0; j < PMSM_NS; j++) acc += C[i][j] * sn[j];
        e_hat[i] = -PMSM_LQ * acc;
    }}
    if (s->started) {{
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
        if (fade < PMSM_R(0.0)) fade = PMSM_R(0.0);
        /* below w_min: the sign of the back-EMF's q component where it disagrees with
           the speed estimate's */
        e_pll = e_perp * s->w / (psi * w2)
                + e_perp * fade * (pmsm_sign(e_q) - pmsm_sign(s->w)) / (psi * PMSM_WMIN);
        w = s->w + PMSM_OBS_T_S * k_i * e_pll;
        /* frequency-locked-loop assist: the back-EMF's rotation since the last sample,
           gated off near lock */
        for (i = 0; i < 2; i++) {{
            pmsm_real acc = Dx[i][0] * (s->x1[0] - s->i_prev[0])
                            + Dx[i][1] * (s->x1[1] - s->i_prev[1]);
            for (j = 0; j < PMSM_NS; j++) acc += C[i][j] * s->s[j];
            e_prev[i] = -PMSM_LQ * acc;
        }}
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
        g = PMSM_R(0.5) * mg * (PMSM_R(1.0) - PMSM_TANH(w_e / PMSM_WMIN) * e_q
                                / PMSM_SQRT(n2 + tiny));
        w += (PMSM_OBS_T_S * PMSM_FLL * PMSM_WPLL) * g * (w_e - s->w);
        theta = pmsm_wrap(th_p + PMSM_OBS_T_S * k_p * e_pll);
    }}
    for (j = 0; j < PMSM_NS; j++) s->s[j] = sn[j];
    for (j = 0; j < 2; j++) {{
        s->x1[j] = x1[j];
        s->i_prev[j] = i_ab[j];
    }}
    s->theta = theta;
    s->w = w;
    s->started = 1;
    *theta_hat = theta;
    *w_hat = w;"""
    name = {"CLESOObserver": "c-leso", "GILESOObserver": "gi-leso",
            "FALESOObserver": "fa-leso"}[type(observer).__name__]
    title = f"{name} back-EMF observer of li-fa-leso with a quadrature PLL"
    doc = (
        f"Observer: {title}.",
        model_doc(m),
        f"Design: {', '.join(f'{k} = {_f(v)!r}' for k, v in observer._own_design().items())};",
        f"PLL: w_pll = {w_pll!r} rad/s, zeta_pll = {zeta_pll!r}, w_min = {w_min!r} rad/s.",
        "Step: the exact ZOH transition over T_s of the observer driven by the current",
        "turning at the PLL speed (linear in that frame) and the voltage integral",
        "(expm of the augmented matrix, recomputed every sample); then",
        "e_hat = -L_q (C s + D_x (x1 - i_k)) and the PLL at theta + T_s w:",
        "eps = -(e_hat . [cos, sin]) w / (psi_ex max(w^2, w_min^2)),",
        "theta = wrap(theta + T_s w + T_s k_p eps), w += T_s k_i eps, plus the",
        "low-speed detector term and the gated FLL assist of QuadraturePLL.step.",
        "First sample: x1 = i_0, s = 0; theta, w unchanged.",
    )
    return CObserver(name=name, title=title, doc=doc, fields=fields, helpers=helpers,
                     init=init, step=step)
