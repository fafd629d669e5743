r"""C text of the li observers' exact ZOH transition in closed form (`_li` uses it): the
half-size complex form of `AbstractBackEMFLESO._transition_c`
(`observers/_back_emf_leso.py`), with the matrix functions of
`observers/_matrix_functions.py`.

In the frame turning at the PLL speed $\hat\omega$ the observer of li-fa-leso (9) (in the
form $\dot y = A_o y + g_i i + g_c\dot\lambda$, $y = [\hat x_1, s]$ complex, size
$p = 1 + n_s/2$) is driven by polynomials in time, so one period is
$y_k = e^{j\hat\omega T_s}[e^X y + \varphi_1(X)g_0 + \varphi_2(X)g_1]$ with
$X = (A_o - j\hat\omega I)T_s$, $g_0 = T_s(g_i i_{k-1} + g_c c)$,
$g_1 = T_s^2 g_i\delta$. Complex numbers are `(re, im)` pairs (`pmsm_cplx`, no
`complex.h`), the coefficients of $X$ and $g_i$ sums of constants times the basis
values $1$, $\hat\omega$, $\max(\hat\omega^2, w_c^2)$ (`b1`, `b2`).

- $p = 2$ (C-LESO (15)-(17), FA-LESO (25)-(28)): `pmsm_phi_pair`, `phi_pair` line by
  line: $X = \mu I + N$ with $N^2 = dI$, every function a pair of complex numbers,
  $\varphi_2$ by Horner's rule of degree 14, directly while the eigenvalue bound
  `pair_radius` is at most 0.5, else at $X/8$ with three doublings.
- $p > 2$ (GI-LESO (29)-(30)): `phi_action` unrolled on the non-zero entries: the Taylor
  series of the action, $\sum_k X^k(y/k! + g_0/(k+1)! + g_1/(k+2)!)$, by Horner's rule
  (one product with $X$ a degree). The row-sum norm $\rho$ of $X$ is taken in the
  observer's own units (`_complex_scale`, as the JAX step switches on it); the period is
  split into $m = \lceil\rho/\theta\rceil$ equal sub-steps ($\theta$ = `SUB_NORM`, at most
  `MAX_SUB`; exact: the inputs on sub-step $j$ are again polynomials, $g_0/m +
  jg_1/m^2$ and $g_1/m^2$), and the degree $K$ is the least whose truncation
  $r^{K+1}e^r/(K+1)!$ at the sub-step norm $r = \rho/m$ is below the unit round-off of
  `pmsm_real` (`_degree_table`): 14 in double at $\rho$ = 0.47 (the JAX step's degree),
  8 in float. The JAX step computes the matrix functions where $\rho > 0.5$
  (`phi_matrix`); both are exact to round-off.
"""

from __future__ import annotations

import math

import numpy as np

from ._c import lit


#: Largest row-sum norm of X (in the observer's units) of one sub-step of the action.
SUB_NORM = 1.0
#: At most this many sub-steps: exact to round-off for norms up to MAX_SUB * SUB_NORM
#: (the JAX step's `phi_matrix`: balanced norms up to about 8).
MAX_SUB = 8

COMPLEX_C = """/* complex numbers (space vectors) as (re, im) pairs */
typedef struct { pmsm_real re, im; } pmsm_cplx;
static inline pmsm_cplx pmsm_c(pmsm_real re, pmsm_real im)
{
    pmsm_cplx z;
    z.re = re;
    z.im = im;
    return z;
}
static inline pmsm_cplx pmsm_cadd(pmsm_cplx a, pmsm_cplx b)
{
    return pmsm_c(a.re + b.re, a.im + b.im);
}
static inline pmsm_cplx pmsm_csub(pmsm_cplx a, pmsm_cplx b)
{
    return pmsm_c(a.re - b.re, a.im - b.im);
}
static inline pmsm_cplx pmsm_cmul(pmsm_cplx a, pmsm_cplx b)
{
    return pmsm_c(a.re * b.re - a.im * b.im, a.re * b.im + a.im * b.re);
}
static inline pmsm_cplx pmsm_cscale(pmsm_cplx a, pmsm_real s)
{
    return pmsm_c(a.re * s, a.im * s);
}
static inline pmsm_cplx pmsm_conj(pmsm_cplx a)
{
    return pmsm_c(a.re, -a.im);
}
"""


def _inv_factorials(n: int, offset: int) -> str:
    return ", ".join(lit(1.0 / math.factorial(j + offset)) for j in range(n))


PAIR_C = f"""/* (x0 I + x1 N) Y + c0 I with Y = m I + N', N'^2 = dd I: (a, b) in place */
static inline void pmsm_times_y(pmsm_cplx *a, pmsm_cplx *b, pmsm_cplx m, pmsm_cplx dd,
                                pmsm_real c0)
{{
    pmsm_cplx a2 = pmsm_cadd(pmsm_cmul(*a, m), pmsm_cmul(dd, *b));
    *b = pmsm_cadd(*a, pmsm_cmul(*b, m));
    *a = pmsm_c(a2.re + c0, a2.im);
}}

/* (x0 I + x1 N)(y0 I + y1 N) with N^2 = d I */
static inline void pmsm_pair_mul(pmsm_cplx x[2], const pmsm_cplx y[2], pmsm_cplx d)
{{
    pmsm_cplx a = pmsm_cadd(pmsm_cmul(x[0], y[0]), pmsm_cmul(d, pmsm_cmul(x[1], y[1])));
    x[1] = pmsm_cadd(pmsm_cmul(x[0], y[1]), pmsm_cmul(x[1], y[0]));
    x[0] = a;
}}

/* E[0], E[1], E[2] = e^Y, phi_1(Y), phi_2(Y) of the 2x2 complex matrix Y = mu I + N,
   N^2 = d I, each as the pair (a, b) of aI + bN (`phi_pair`): phi_2 by Horner's rule of
   degree 14 of sum_j Y^j/(j + 2)!, phi_1 = I + Y phi_2, e^Y = I + Y phi_1; directly at Y
   while |Re mu| + |Im mu| + (|Re d| + |Im d|)^(1/2) <= 0.5, else at Y/8 and three
   doublings: e^2Y = (e^Y)^2, 2 phi_1(2Y) = phi_1(Y)(e^Y + I),
   4 phi_2(2Y) = phi_2(Y)(e^Y + I) + phi_1(Y) */
static void pmsm_phi_pair(pmsm_cplx mu, pmsm_cplx d, pmsm_cplx E[3][2])
{{
    static const pmsm_real inv_f[15] = {{{_inv_factorials(15, 2)}}};
    pmsm_real rad = PMSM_FABS(mu.re) + PMSM_FABS(mu.im)
                    + PMSM_SQRT(PMSM_FABS(d.re) + PMSM_FABS(d.im));
    int nsq = rad <= PMSM_R(0.5) ? 0 : 3, j, q;
    pmsm_real sc = nsq ? PMSM_R(0.125) : PMSM_R(1.0);
    pmsm_cplx m = pmsm_cscale(mu, sc), dd = pmsm_cscale(d, sc * sc), a, b;
    a = pmsm_c(inv_f[14] * m.re + inv_f[13], inv_f[14] * m.im);
    b = pmsm_c(inv_f[14], PMSM_R(0.0));
    for (j = 12; j >= 0; j--) pmsm_times_y(&a, &b, m, dd, inv_f[j]);
    E[2][0] = a;
    E[2][1] = b;
    pmsm_times_y(&a, &b, m, dd, PMSM_R(1.0));
    E[1][0] = a;
    E[1][1] = b;
    pmsm_times_y(&a, &b, m, dd, PMSM_R(1.0));
    E[0][0] = a;
    E[0][1] = b;
    for (j = 0; j < 3; j++) E[j][1] = pmsm_cscale(E[j][1], sc);  /* to the basis I, N */
    for (q = 0; q < nsq; q++) {{
        pmsm_cplx e0p1[2];
        e0p1[0] = pmsm_c(E[0][0].re + PMSM_R(1.0), E[0][0].im);
        e0p1[1] = E[0][1];
        pmsm_pair_mul(E[2], e0p1, d);
        E[2][0] = pmsm_cscale(pmsm_cadd(E[2][0], E[1][0]), PMSM_R(0.25));
        E[2][1] = pmsm_cscale(pmsm_cadd(E[2][1], E[1][1]), PMSM_R(0.25));
        pmsm_pair_mul(E[1], e0p1, d);
        E[1][0] = pmsm_cscale(E[1][0], PMSM_R(0.5));
        E[1][1] = pmsm_cscale(E[1][1], PMSM_R(0.5));
        e0p1[0] = E[0][0];
        pmsm_pair_mul(E[0], e0p1, d);
    }}
}}
"""


def _degree_table(u: float, k_max: int) -> list[float]:
    """`theta[K]`, K = 0..k_max: the largest norm r with r^(K+1) e^r / (K+1)! <= u (the
    remainder of the degree-K series, relative to its inputs), by bisection."""
    out = [0.0]
    for K in range(1, k_max + 1):
        lo, hi = 0.0, 64.0
        for _ in range(200):
            r = 0.5 * (lo + hi)
            if (K + 1) * math.log(r) + r - math.lgamma(K + 2) <= math.log(u):
                lo = r
            else:
                hi = r
        out.append(lo)
    return out


def _k_max(u: float) -> int:
    theta = _degree_table(u, 40)
    return next(K for K in range(1, 41) if theta[K] >= SUB_NORM)


def degree_tables() -> tuple[str, int]:
    """C text of the degree tables (double and float: unit round-off 2^-53, 2^-24) and
    of the inverse factorials the action's Horner rule reads; the largest degree."""
    k64, k32 = _k_max(2.0 ** -53), _k_max(2.0 ** -24)
    t64, t32 = _degree_table(2.0 ** -53, k64), _degree_table(2.0 ** -24, k32)
    k_max = max(k64, k32)

    def arr(values):
        return ", ".join(lit(v) for v in values)

    text = f"""/* the action's degree K: the least with theta[K] >= the sub-step norm r, theta[K]
   the largest r with r^(K+1) e^r / (K+1)! below the unit round-off of pmsm_real */
#define PMSM_KMAX (sizeof(pmsm_real) == sizeof(float) ? {k32} : {k64})
static const pmsm_real pmsm_theta64[{k64 + 1}] = {{{arr(t64)}}};
static const pmsm_real pmsm_theta32[{k32 + 1}] = {{{arr(t32)}}};
/* 1/k!, k = 0..{k_max + 2} */
static const pmsm_real pmsm_inv_fact[{k_max + 3}] = {{{_inv_factorials(k_max + 3, 0)}}};
#define PMSM_SUB_NORM {lit(SUB_NORM)}
#define PMSM_MAX_SUB {MAX_SUB}
"""
    return text, k_max


# --- the coefficients as C expressions ------------------------------------------------

def part_expr(coef, factor: float = 1.0) -> str | None:
    """The C expression of `factor * (c0 + c1 b1 + c2 b2)` for the real coefficients
    `coef` (3,) over the basis 1, w, max(w^2, w_c^2); None where all are zero."""
    terms = []
    for k, c in enumerate(np.asarray(coef, float)):
        if c != 0.0:
            terms.append(lit(c * factor) + ("" if k == 0 else f" * b{k}"))
    return " + ".join(terms) if terms else None


def entry(coef, factor: float = 1.0, extra_im: str | None = None):
    """`(re, im)` C expressions (None: structurally zero) of a complex coefficient
    `coef` (3,) times `factor`, plus `extra_im` in the imaginary part."""
    coef = np.asarray(coef, complex)
    re, im = part_expr(coef.real, factor), part_expr(coef.imag, factor)
    if extra_im is not None:
        im = extra_im if im is None else f"{im} + {extra_im}"
    return re, im


def cplx_expr(parts) -> str:
    re, im = parts
    return f"pmsm_c({re or 'PMSM_R(0.0)'}, {im or 'PMSM_R(0.0)'})"


ZERO = "pmsm_c(PMSM_R(0.0), PMSM_R(0.0))"


def cterm(parts, var: str) -> str | None:
    """The C expression of the complex coefficient `parts` (re, im) times the complex
    `var`; None where the coefficient is zero."""
    re, im = parts
    if re is None and im is None:
        return None
    if im is None:
        return var if re == lit(1.0) else f"pmsm_cscale({var}, {re})"
    return f"pmsm_cmul({cplx_expr(parts)}, {var})"


def _abs_expr(name: str, parts) -> str:
    re, im = parts
    if re is not None and im is not None:
        return f"PMSM_SQRT({name}r * {name}r + {name}i * {name}i)"
    return f"PMSM_FABS({name}{'r' if re is not None else 'i'})"


def _ratio_expr(c: float, e: int) -> str:
    """`c * sb^e` as C (sb = sqrt(b2), isb = 1/sb)."""
    f = {0: [], 1: ["sb"], 2: ["sb", "sb"], -1: ["isb"], -2: ["isb", "isb"]}[e]
    return " * ".join(([] if c == 1.0 else [lit(c)]) + f)


def action(X, gi, scale, p: int, g_c: str) -> str:
    """C statements of the GI-LESO's transition (`p > 2`): from the locals `y[p]` (the
    complex state), `ip` (i_(k-1)), `c`, `delta` (complex) and `rot`, the new state in
    `y` (stationary frame). `X[i][j]`: `(re, im)` C expressions of X (None: zero);
    `gi[i]`: `(re, im)` of g_i T_s; `scale`: `(c_i, e_i)` of the observer's units
    d_i = c_i sqrt(b2)^e_i; `g_c`: the C expression of T_s / L_q."""
    nz = [[X[i][j] != (None, None) for j in range(p)] for i in range(p)]
    L = []
    decl = []
    for i in range(p):
        for j in range(p):
            re, im = X[i][j]
            for part, ex in (("r", re), ("i", im)):
                if ex is not None:
                    decl.append(f"x{i}_{j}{part} = {ex}")
    L.append(f"        pmsm_real {', '.join(decl)};")
    vectors = ", ".join(f"{v}[{p}]" for v in ("g0", "g1", "a", "b", "v", "nv"))
    L.append(f"        pmsm_cplx {vectors};")
    L.append("        pmsm_real rho = PMSM_R(0.0), r, row, inv_m, sr, si;")
    L.append("        const pmsm_real *theta_k = sizeof(pmsm_real) == sizeof(float) "
             "? pmsm_theta32 : pmsm_theta64;")
    L.append("        int m = 1, K, k, j, i;")
    if any(e != 0 for _, e in scale):
        L.append("        pmsm_real sb = PMSM_SQRT(b2), isb = PMSM_R(1.0) / sb;")
    L.append("        /* the row-sum norm of X in the observer's units (_complex_scale) */")
    for i in range(p):
        terms = []
        for j in range(p):
            if nz[i][j]:
                a_ = _abs_expr(f"x{i}_{j}", X[i][j])
                rat = _ratio_expr(scale[j][0] / scale[i][0], scale[j][1] - scale[i][1])
                terms.append(a_ if not rat else f"{a_} * {rat}")
        if terms:
            L.append(f"        row = {' + '.join(terms)};")
            L.append("        if (row > rho) rho = row;")
    L.append("        while (m < PMSM_MAX_SUB && rho > (pmsm_real)m * PMSM_SUB_NORM) m++;")
    L.append("        inv_m = PMSM_R(1.0) / (pmsm_real)m;")
    L.append("        r = rho * inv_m;")
    L.append("        for (K = 1; K < PMSM_KMAX && theta_k[K] < r; K++) {}")
    L.append("        /* sub-step X / m */")
    for i in range(p):
        for j in range(p):
            for part, ex in zip("ri", X[i][j]):
                if ex is not None:
                    L.append(f"        x{i}_{j}{part} *= inv_m;")
    L.append("        /* the inputs over the period: g0 = T_s (g_i i + g_c c), "
             "g1 = T_s^2 g_i delta */")
    for i in range(p):
        g0 = cterm(gi[i], "ip") or ZERO
        if i == 0:
            g0 = f"pmsm_cadd({g0}, pmsm_cscale(c, {g_c}))"
        gd = cterm(gi[i], "delta")
        g1 = f"pmsm_cscale({gd}, PMSM_OBS_T_S)" if gd else ZERO
        L.append(f"        g0[{i}] = {g0};")
        L.append(f"        g1[{i}] = {g1};")
    L.append("        for (j = 0; j < m; j++) {")
    L.append(f"            for (k = 0; k < {p}; k++) {{")
    L.append("                /* sub-step j: g0/m + j g1/m^2 and g1/m^2 */")
    L.append("                a[k] = pmsm_cscale(pmsm_cadd(g0[k], pmsm_cscale(g1[k], "
             "(pmsm_real)j * inv_m)), inv_m);")
    L.append("                b[k] = pmsm_cscale(g1[k], inv_m * inv_m);")
    L.append("                v[k] = pmsm_cadd(pmsm_cadd(pmsm_cscale(y[k], pmsm_inv_fact[K]),")
    L.append("                                           pmsm_cscale(a[k], "
             "pmsm_inv_fact[K + 1])),")
    L.append("                                 pmsm_cscale(b[k], pmsm_inv_fact[K + 2]));")
    L.append("            }")
    L.append("            for (k = K - 1; k >= 0; k--) {")
    L.append("                pmsm_real f0 = pmsm_inv_fact[k], f1 = pmsm_inv_fact[k + 1], "
             "f2 = pmsm_inv_fact[k + 2];")
    for i in range(p):
        sr, si = [], []
        for j in range(p):
            if not nz[i][j]:
                continue
            re, im = X[i][j]
            n = f"x{i}_{j}"
            if re is not None:
                sr.append(f"{n}r * v[{j}].re")
                si.append(f"{n}r * v[{j}].im")
            if im is not None:
                sr.append(f"- {n}i * v[{j}].im")
                si.append(f"{n}i * v[{j}].re")
        sr_t = " ".join(t if t.startswith("-") or not k else f"+ {t}"
                        for k, t in enumerate(sr)) or "PMSM_R(0.0)"
        si_t = " + ".join(si) or "PMSM_R(0.0)"
        L.append(f"                sr = {sr_t};")
        L.append(f"                si = {si_t};")
        # the inputs' terms where they are not zero (g0[0] has the voltage's)
        ins = ([f"a[{i}].%s * f1"] if i == 0 or gi[i] != (None, None) else []) + \
              ([f"b[{i}].%s * f2"] if gi[i] != (None, None) else [])
        for part, acc in (("re", "sr"), ("im", "si")):
            terms = " + ".join([acc, f"y[{i}].{part} * f0"] + [t % part for t in ins])
            L.append(f"                nv[{i}].{part} = {terms};")
    L.append(f"                for (i = 0; i < {p}; i++) v[i] = nv[i];")
    L.append("            }")
    L.append(f"            for (i = 0; i < {p}; i++) y[i] = v[i];")
    L.append("        }")
    L.append(f"        for (i = 0; i < {p}; i++) y[i] = pmsm_cmul(rot, y[i]);")
    return "\n".join(L)
