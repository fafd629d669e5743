r"""Objective of the gain tuner: closed-loop metrics of a batch of runs plus a smooth
stability/feasibility penalty from the equilibrium analysis.

**Per scenario** $j$ (one sensorless run, `tuning.scenarios`), with the angle error
$\tilde\theta(t)$ (true minus estimate) and the speed-estimate error
$\tilde\omega(t) = \omega - \hat\omega$, both sampled every `save_every` periods:

- position-error energy after the transient, as an RMS angle (deg):
  $p_j = \sqrt{\overline{\tilde\theta^2}}$ over $t \ge t_{tr}$; under inductance
  mismatch it contains the static error of the designed equilibrium;
- settling-time surrogate (s): with $\tilde\theta_\infty$ the mean of $\tilde\theta$ over
  $t \ge t_{tr}$, $\tau_j = \sqrt{4\int_0^T t\,(\tilde\theta - \tilde\theta_\infty)^2 dt
  / \tilde\theta_0^2}$, which is exactly the time constant $\tau$ for an exponential
  decay $\tilde\theta_0 e^{-t/\tau}$ (a smooth, time-weighted error energy);
- speed-estimate noise (rad/s): the standard deviation of $\tilde\omega$ over
  $t \ge t_{tr}$ with current-sensor noise on;
- stability penalty $s_j$ (below).

$\ell_j = w_{pos}\,p_j/\theta_u + w_{set}\,\tau_j/\tau_u + w_{noise}\,\sigma_j/\sigma_u
+ w_{stab}\,s_j$ (dimensionless); a run that diverged (`status != 0`) or produced a
non-finite value gets $\ell_j$ = `diverged_loss` (finite; the gradient of that branch is 0).

**Aggregates.** Average: $\frac1n\sum_j \ell_j$. Robust: the smooth maximum
$T\log\big(\frac1n\sum_j e^{\ell_j/T}\big)$ (log-mean-exp at temperature $T$, in loss
units), which lies between the average and the maximum and tends to the maximum as
$T \to 0$.

**No regression** (`"no_regression"`, the main job's default). The robust aggregate is
dominated by the hardest scenarios, so minimising it alone buys their improvement with
regressions elsewhere (other speeds, other mismatch). The default objective minimises
it subject to every training scenario's loss staying within a relative tolerance
$\tau$ (`regression_tol`) of the baseline's $\ell_j^{b}$ (the paper's design, the
tuner's start):
$$L_{robust} + w\sum_j \mathrm{sp}_4\Big(\frac{r_j - \tau/2}{\tau}\Big),\qquad
r_j = \frac{\ell_j - \ell_j^{b}}{\ell_j^{b}},\qquad
\mathrm{sp}_4(x) = \tfrac14\log(1 + e^{4x})$$
with $w$ = `w_regression` (loss units). A smooth penalty rather than a hard constraint
because the optimisers (Adam, BFGS, Levenberg-Marquardt, the gradient-free searches) are
unconstrained and work on unconstrained variables already; the hinge sits at $\tau/2$
and rises over a fraction of $\tau$, so the iterates stay inside the tolerance with a
margin, and far inside it the penalty is nearly flat (at $r_j = 0$ its slope is a tenth
of that at the boundary: a mild pull towards improving every scenario, not a second
objective). The constraint itself is enforced exactly by the optimisers' selection: for
this objective a design becomes the best iterate only if no training scenario's loss
exceeds the baseline's by more than $\tau$ (`within_tolerance`). The start (the
baseline) satisfies it, so the returned design never has a training regression above
$\tau$. Held-out and validation scenarios are not constrained: the report checks them.

**Stability/feasibility penalty** (generic over the observer contract,
`pmsmjax.observers.AbstractObserver`). At each scenario's operating point
`OperatingPoint(w_0, i_0 = (0, i_q))`, with the observer's mismatched model
(`observer.with_motor`) and the tuned design, the error dynamics `observer.error_rhs`
(for zhang2022's observers (11) with the design's gains at the operating point, fal
feedback for the ESO, the AFO's PI law (53) as $g_2 = [0, -k_p]$, $g_3 = [0, -k_i]$)
have a designed (principal) equilibrium near $\tilde\theta = 0$ and possibly others.
Their locations come from the analysis (`pmsmjax.analysis.equilibria_traced`, or the
family's own route where it declares one, `observer.fast_equilibria`, both on the grid
`n_grid`; bracketing and refinement: not differentiable, so they are computed under
`stop_gradient`) and are then refined by two Newton steps on the differentiable
right-hand side, which by the implicit-function theorem gives their exact first-order
dependence on the design. For each equilibrium the Jacobian (`jax.jacfwd` of
`error_rhs`; zhang2022 (37) for the ESO) is scaled as in the analysis module (states by
`observer.error_scale`, time by $|\omega_0|$), and its characteristic polynomial
$s^n + c_1 s^{n-1} + \dots + c_n$ (`pmsmjax.analysis.charpoly`) gives the Routh-Hurwitz
quantities (`routh_margins`): the odd coefficients $c_1, c_3, \dots$, $c_n$ and the
Hurwitz determinants $\Delta_2, \dots, \Delta_{n-1}$ (for $n = 4$:
$m = (c_1, c_3, c_4, c_1c_2 - c_3, (c_1c_2-c_3)c_3 - c_1^2c_4)$), each divided by its
degree in a spectral scale $\rho$ (the mean root magnitude); all are positive iff the
equilibrium is stable (the exact test `routh_hurwitz` uses: $\Delta_1 = c_1$,
$\Delta_n = c_n\Delta_{n-1}$). The penalty $s_j$ sums

- designed equilibrium, Hurwitz with margin: $\sum_k \mathrm{sp}(-m_k)$ for the matrix
  shifted by the margin $\sigma = $ `hurwitz_margin` (rad/s), i.e. all poles left of
  $-\sigma$;
- every other equilibrium *not* stable (feasibility, zhang2022 Sec. IV):
  $\mathrm{sp}(\mathrm{smin}_k\, m_k)$;
- the design's own margins (`design_penalty`; for zhang2022's `GainSchedule` the slope
  bound $\kappa$ of the reduction behind the ESO family's own equilibrium route,
  `reduction_kappa`, above 0.05: the minimum-norm gains (25) always satisfy it,
  null-space components can violate it, and there that analysis does not apply);
- the fast poles resolvable at the sampling rate (`sampling_penalty`): the design's own
  pole bounds where it has them (`GainSchedule.pole_bounds`), else an estimate from the
  designed equilibrium's characteristic polynomial,

with $\mathrm{sp}(x) = \log(1 + e^{30x})/30$ and smin a smooth minimum. The penalty is
smooth and never NaN for a nondegenerate equilibrium, and its first two parts vanish
(in the limit) exactly where the exact test says feasible and Hurwitz. The report checks
feasibility with the exact (non-smooth) classification as well (`feasibility`).

**Limits.** The analysis holds the gains fixed at the operating point, while the observer
schedules them with its own $\hat\omega$; and "no other stable equilibrium" does not
exclude other attractors (a slipping orbit: see the notebook). The simulated runs, with
their 30 deg initial error, are what checks the large-signal behaviour.
"""

from __future__ import annotations

import inspect
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import pmsmjax as pj
from pmsmjax.analysis import charpoly, equilibria_traced
from pmsmjax.observers import OperatingPoint

from ._parametrise import AbstractDesign, reduction_kappa  # noqa: F401  (re-exported)
from .scenarios import (
    ScenarioSet,
    TuningConfig,
    make_observer,
    observer_motor,
    operating_current,
    simulate_scenarios,
)


_SHARP = 30.0  # sharpness of the softplus hinge of the penalty (1 / normalised margin)
_EPS = 1e-12


class Metrics(eqx.Module):
    r"""Per-scenario metrics (arrays with a leading scenario axis).

    - `pos_rms_deg`: RMS angle error after the transient (deg).
    - `theta_ss_deg`: mean angle error after the transient (deg): the static error.
    - `settle_s`: settling-time surrogate (s).
    - `noise_rad_s`: standard deviation of the speed-estimate error after the transient.
    - `w_bias_rad_s`: its mean, $\omega - \hat\omega$ (rad/s; reported, not in the loss:
      with null-space components $\nu \ne 0$ the equilibrium has $\hat\omega \ne \omega$
      under mismatch).
    - `stab_penalty`: the smooth stability/feasibility penalty (before `w_stab`).
    - `ok`: the run did not diverge.
    - `loss`: the per-scenario loss.
    """

    pos_rms_deg: jnp.ndarray
    theta_ss_deg: jnp.ndarray
    settle_s: jnp.ndarray
    noise_rad_s: jnp.ndarray
    w_bias_rad_s: jnp.ndarray
    stab_penalty: jnp.ndarray
    ok: jnp.ndarray
    loss: jnp.ndarray


# ---------------------------------------------------------------------------------------
# Trajectory metrics
# ---------------------------------------------------------------------------------------

def _safe_sqrt(x):
    return jnp.sqrt(jnp.maximum(x, 0.0) + _EPS)


def trajectory_metrics(traj: pj.Trajectory, config: TuningConfig) -> dict:
    """`pmsmjax.trajectory_metrics` with `config`'s transient, sampling and initial error:
    RMS error after the transient (deg), static error (deg), settling surrogate (s),
    speed-estimate noise and mean error (rad/s) and `ok` of a batched `Trajectory`."""
    return pj.trajectory_metrics(traj, t_transient=config.t_transient, T_s=config.T_s,
                                 save_every=config.save_every,
                                 theta_err0=math.radians(config.theta_err0_deg))


# ---------------------------------------------------------------------------------------
# Stability and feasibility
# ---------------------------------------------------------------------------------------

def _hurwitz_minors(c, n: int) -> list:
    r"""Leading principal minors $\Delta_2, \dots, \Delta_{n-1}$ of the Hurwitz matrix
    $H_{ij} = c_{2j-i}$ (1-based; $c_0 = 1$, $c_k = 0$ outside $0..n$) of the monic
    polynomial with coefficients `c = [1, c1, ..., cn]` (last axis): exact polynomials
    in the coefficients, by cofactor expansion along the first row with the structural
    zeros and ones of $H$ skipped at trace time (no division, so always finite)."""
    def entry(i, j):  # 0-based
        k = 2 * (j + 1) - (i + 1)
        if k < 0 or k > n:
            return 0
        return 1 if k == 0 else c[..., k]

    def mul(a, b):
        if isinstance(a, int) and a == 0 or isinstance(b, int) and b == 0:
            return 0
        if isinstance(a, int) and a == 1:
            return b
        if isinstance(b, int) and b == 1:
            return a
        return a * b

    def add(a, b, sign):
        if isinstance(b, int) and b == 0:
            return a
        if isinstance(a, int) and a == 0:
            return b if sign > 0 else -b
        return a + b if sign > 0 else a - b

    memo = {}

    def det(row, cols):  # rows row..k-1, the columns `cols` (a tuple, increasing)
        if not cols:
            return 1
        key = (row, cols)
        if key not in memo:
            out = 0
            for pos, j in enumerate(cols):
                e = entry(row, j)
                if isinstance(e, int) and e == 0:
                    continue
                term = mul(e, det(row + 1, cols[:pos] + cols[pos + 1:]))
                out = add(out, term, 1 if pos % 2 == 0 else -1)
            memo[key] = out
        return memo[key]

    zero = jnp.zeros_like(c[..., 0])
    out = []
    for k in range(2, n):
        d = det(0, tuple(range(k)))
        out.append(zero + d if isinstance(d, int) else d)
    return out


def routh_margins(A):
    r"""Normalised Routh-Hurwitz quantities of a square matrix `A` `(n, n)` (all > 0 iff
    it is Hurwitz): the coefficients $c_k$ of its characteristic polynomial
    (`pmsmjax.analysis.charpoly`) for odd $k < n$, $c_n$, and the Hurwitz determinants
    $\Delta_2, \dots, \Delta_{n-1}$ (for $n = 4$: $c_1, c_3, c_4, c_1c_2 - c_3,
    (c_1c_2 - c_3)c_3 - c_1^2c_4$).

    Each is divided by its degree in a spectral scale $\rho$, the mean over $k$ of
    $\sqrt[k]{|c_k|/\binom{n}{k}}$ (each equals the root magnitude when all roots are
    equal), so healthy margins are O(1)."""
    c = charpoly(A)
    n = A.shape[-1]
    root = lambda x, k: (x * x + 1e-24) ** (0.5 / k)  # noqa: E731  (smooth |x|^(1/k))
    rho = sum(root(c[k] / math.comb(n, k), k) for k in range(1, n + 1)) / n
    rho = jnp.maximum(rho, 1e-6)
    ks = [k for k in range(1, n, 2)] + [n]
    m = [c[k] / rho ** k for k in ks]
    for k, d in zip(range(2, n), _hurwitz_minors(c, n)):
        m.append(d / rho ** (k * (k + 1) // 2))
    return jnp.stack(m)


def pole_size(A):
    r"""A smooth estimate of the largest pole magnitude of `A` `(n, n)`:
    $\max_k \sqrt[k]{|c_k|}$ over its characteristic polynomial. For poles with negative
    real parts $c_1 = \sum_i |\mathrm{Re}\,\lambda_i| + \dots$ bounds the fastest real pole
    and $\sqrt{c_2}$ the magnitude of a lightly damped pair; Fujiwara's bound says no pole
    exceeds twice it."""
    c = charpoly(A)
    n = A.shape[-1]
    return jnp.max(jnp.stack([(c[k] * c[k] + 1e-24) ** (0.5 / k) for k in range(1, n + 1)]))


_POLE_TS_MAX = 0.8  # fastest designed pole times T_s


def sampling_penalty(design, w0, T_s, A=None):
    r"""Keep the fast poles resolvable at the sampling rate: for each pole bound $p$
    (1/s), $\mathrm{sp}((p\,T_s - 0.8)/0.2)$, summed. The bounds are the design's own
    (`AbstractDesign.pole_bounds`; for `GainSchedule` $p(\zeta, \omega) = \omega(\zeta +
    \sqrt{\zeta^2 + 1})$ of the flux and speed/angle poles at `w0`), else
    `pole_size(A) |w0|` of the designed equilibrium's scaled Jacobian `A` (time in units
    of $1/|\omega_0|$). The discrete observers integrate by forward Euler, which turns
    unstable for poles beyond about $2/T_s$."""
    p = design.pole_bounds(w0) if isinstance(design, AbstractDesign) else None
    if p is None:
        if A is None:
            return jnp.zeros(())
        p = pole_size(A) * jnp.abs(w0)
    return jnp.sum(_sp((jnp.asarray(p) * T_s - _POLE_TS_MAX) / 0.2))


def design_penalty(design, observer, op):
    r"""$\sum_k \mathrm{sp}(-m_k)$ over the design's own margins
    (`AbstractDesign.design_margins`; `GainSchedule`: zhang2022's reduction slope bound
    $\kappa$ above 0.05), 0 for a design without any."""
    m = design.design_margins(observer, op) if isinstance(design, AbstractDesign) else None
    if m is None:
        return jnp.zeros(())
    return jnp.sum(_sp(-m))


def _sp(x):
    return jax.nn.softplus(_SHARP * x) / _SHARP


def _smin(m, tau=0.05):
    return -tau * jax.scipy.special.logsumexp(-m / tau)


class EquilibriumSet(eqx.Module):
    """Equilibria of the error dynamics at every scenario's operating point
    (`equilibria`; leading axis: scenario, then `K` slots).

    - `x`: states `(n, K, n_x)` in the observer's `coordinates` (SI; zhang2022's
      observers: V s, V s, rad, rad/s), 0 in invalid slots; `theta` (rad).
    - `valid`, `stable`: `(n, K)`; `principal`: index of the designed equilibrium `(n,)`.
    - `status`: 0 ok, 2 no equilibrium, -1 the analysis failed (degenerate).
    """

    x: jnp.ndarray
    theta: jnp.ndarray
    valid: jnp.ndarray
    stable: jnp.ndarray
    principal: jnp.ndarray
    status: jnp.ndarray


#: Equilibrium slots per operating point (more zeros than slots: status -1).
MAX_ROOTS = 8


def _point(config: TuningConfig, drive, kind, design, k_d, k_q, speed_pu, load_pu):
    """The observer (registry, design applied, mismatched model), the operating point and
    the true machine of one scenario."""
    obs = make_observer(kind, drive, design, motor=observer_motor(drive, k_d, k_q))
    op = OperatingPoint(speed_pu * float(drive.w_rated), operating_current(drive, load_pu))
    return obs, op, drive.three_phase_motor


def _raw_equilibria(config, drive, kind, design, k_d, k_q, speed_pu, load_pu):
    """The family's own route where it has one (`observer.fast_equilibria`, e.g.
    zhang2022's reduction for the ESO's fal feedback) on the tuner's grid, else the
    generic route; as `pmsmjax.analysis.equilibria(method="auto")`, with `n_grid`."""
    obs, op, plant = _point(config, drive, kind, design, k_d, k_q, speed_pu, load_pu)
    # a family route that does not take a grid (the contract's optional argument) keeps
    # its own
    grid = ({"n_grid": config.n_grid}
            if "n_grid" in inspect.signature(obs.fast_equilibria).parameters else {})
    fast = obs.fast_equilibria(plant, op, **grid)
    if fast is not None:
        return fast
    tol = float(jnp.finfo(op.w_m.dtype).eps) ** 0.6  # as `pmsmjax.analysis.equilibria`
    return equilibria_traced(obs, plant, op, method="generic", n_grid=config.n_grid,
                             max_roots=MAX_ROOTS, tol=tol)


def equilibria(design, config: TuningConfig, scenarios: ScenarioSet, kind: str | None = None
               ) -> EquilibriumSet:
    """Every equilibrium of the error dynamics at each scenario's operating point, for
    `design` (`pmsmjax.analysis.equilibria_traced`, or the family's own route
    `observer.fast_equilibria`, on the grid `config.n_grid`: not differentiable; see
    `stability_penalty` for how the loss uses them)."""
    # one compiled program whether `kind` is left out, None or `config.observer`
    return _equilibria_jit(design, config, scenarios,
                           config.observer if kind is None else kind)


@eqx.filter_jit
def _equilibria_jit(design, config, scenarios, kind):
    drive = config.drive()

    def one(k_d, k_q, speed_pu, load_pu):
        eq = _raw_equilibria(config, drive, kind, design, k_d, k_q, speed_pu, load_pu)
        valid = eq.valid & (eq.status == 0)
        return EquilibriumSet(x=jnp.where(valid[:, None], eq.x, 0.0), theta=eq.theta,
                              valid=valid, stable=eq.stable & valid,
                              principal=eq.principal, status=eq.status)

    return jax.vmap(one)(scenarios.k_d, scenarios.k_q, scenarios.speed_pu,
                         scenarios.load_pu)


def stability_penalty(design, config: TuningConfig, scenarios: ScenarioSet,
                      eqs: EquilibriumSet, *, kind: str | None = None):
    """Smooth penalty per scenario (see the module docstring); differentiable in `design`.

    `eqs` are the equilibria from `equilibria` (for this design, or a nearby one: they
    are only starting points of the two Newton steps). Returns `(penalty, margin)`: the
    penalty `(n,)` and the smooth minimum of the normalised Routh quantities of the
    designed equilibrium (> 0: Hurwitz).
    """
    drive = config.drive()
    kind = config.observer if kind is None else kind
    eqs = jax.lax.stop_gradient(eqs)

    def one(k_d, k_q, speed_pu, load_pu, eq):
        obs, op, plant = _point(config, drive, kind, design, k_d, k_q, speed_pu, load_pu)
        w0 = op.w_m
        d = 1.0 / obs.error_scale(op, plant)
        n = d.shape[0]
        eye = jnp.eye(n)

        def rhs(x):
            return obs.error_rhs(x, op, plant)

        def refine(x):
            for _ in range(2):
                step = jnp.linalg.solve(jax.jacfwd(rhs)(x), rhs(x))
                x = jnp.where(jnp.all(jnp.isfinite(step)), x - step, x)
            return x

        def scaled_jac(x):
            A = jax.jacfwd(rhs)(x)
            return A * d[:, None] / d[None, :] / jnp.abs(w0)

        valid = eq.valid
        A = jax.vmap(lambda x: scaled_jac(refine(x)))(eq.x)
        K = valid.shape[0]
        principal = (jnp.arange(K) == eq.principal) & valid
        sigma = config.hurwitz_margin / jnp.abs(w0)
        m_shift = jax.vmap(routh_margins)(A + sigma * eye)
        m = jax.vmap(routh_margins)(A)
        pen_p = jnp.sum(_sp(-m_shift), -1)
        pen_o = _sp(jax.vmap(_smin)(m))
        # the designed equilibrium: if the search failed, use the origin
        A0 = scaled_jac(refine(jnp.zeros(n, A.dtype)))
        pen_0 = jnp.sum(_sp(-routh_margins(A0 + sigma * eye)))
        has_p = jnp.any(principal)
        pen = jnp.where(has_p, jnp.sum(jnp.where(principal, pen_p, 0.0)), pen_0)
        pen = pen + jnp.sum(jnp.where(valid & ~principal, pen_o, 0.0))
        pen = pen + design_penalty(design, obs, op)
        A_p = jnp.where(has_p, jnp.sum(jnp.where(principal[:, None, None], A, 0.0), 0), A0)
        pen = pen + sampling_penalty(design, w0, config.T_s, A_p)
        margin = jnp.where(has_p, jnp.sum(jnp.where(principal[:, None], m, 0.0), 0),
                           routh_margins(A0))
        pen = jnp.where(jnp.isfinite(pen), pen, 10.0)
        return pen, _smin(margin)

    return jax.vmap(one)(scenarios.k_d, scenarios.k_q, scenarios.speed_pu,
                         scenarios.load_pu, eqs)


@eqx.filter_jit
def _principal_max_eig(design, config, scenarios, eqs, kind):
    drive = config.drive()

    def one(k_d, k_q, speed_pu, load_pu, eq):
        obs, op, plant = _point(config, drive, kind, design, k_d, k_q, speed_pu, load_pu)
        A = jax.jacfwd(lambda x: obs.error_rhs(x, op, plant))(eq.x[eq.principal])
        return jnp.max(jnp.real(jnp.linalg.eigvals(A)))

    return jax.vmap(one)(scenarios.k_d, scenarios.k_q, scenarios.speed_pu,
                         scenarios.load_pu, eqs)


def _chunks(scenarios: ScenarioSet, chunk: int | None) -> list:
    """`scenarios` in batches of `chunk` (the last padded with its final scenario)."""
    n = scenarios.n
    if chunk is None or chunk == n:
        return [scenarios]
    if not (isinstance(chunk, int) and chunk >= 1):
        raise ValueError(f"`chunk` must be a positive integer; got {chunk!r}.")
    n_pad = -n % chunk
    idx = np.concatenate([np.arange(n), np.full(n_pad, n - 1)])
    return [jax.tree_util.tree_map(lambda a: a[idx[k:k + chunk]], scenarios)
            for k in range(0, n + n_pad, chunk)]


def _concat(parts, n):
    return jax.tree_util.tree_map(lambda *a: np.concatenate(a)[:n], *parts)


def feasibility(design, config: TuningConfig, scenarios: ScenarioSet, *,
                kind: str | None = None, chunk: int | None = None) -> dict:
    """Exact (non-smooth) check per scenario, from the analysis (`equilibria`:
    `pmsmjax.analysis.equilibria_traced` or the family's own route; Routh-Hurwitz on
    each equilibrium).

    Returns numpy arrays: `feasible` (the analysis succeeded, the designed equilibrium is
    stable and no other equilibrium is: Sec. IV's condition, plus Hurwitz),
    `principal_stable`, `n_nonzero`, `principal_theta_deg` (the static error the analysis
    predicts), `stable_other_theta_deg` (a stable non-designed equilibrium, NaN if none),
    `max_real_eig` (of the designed equilibrium's Jacobian, 1/s) and `status`.
    `chunk`: as in `evaluate`.
    """
    kind = config.observer if kind is None else kind
    parts = []
    for part in _chunks(scenarios, chunk):
        eqs = equilibria(design, config, part, kind)
        r = jax.tree_util.tree_map(np.asarray, eqs)
        mre = np.asarray(_principal_max_eig(design, config, part, eqs, kind))
        parts.append((r, mre))
    r = _concat([p[0] for p in parts], scenarios.n)
    mre = np.concatenate([p[1] for p in parts])[:scenarios.n]
    n = r.valid.shape[0]
    idx = np.arange(n)
    principal = r.principal
    other = r.valid & (np.arange(r.valid.shape[1])[None, :] != principal[:, None])
    st_o = r.stable & other
    th_o = np.where(st_o, np.abs(r.theta), np.inf)
    k = np.argmin(th_o, axis=1)
    has_o = np.any(st_o, axis=1)
    p_stable = r.stable[idx, principal] & r.valid[idx, principal]
    ok = r.status == 0
    return dict(
        feasible=ok & p_stable & ~has_o,
        principal_stable=p_stable,
        n_nonzero=np.where(ok, other.sum(1), 0),
        status=r.status,
        principal_theta_deg=np.where(ok, np.degrees(r.theta[idx, principal]), np.nan),
        stable_other_theta_deg=np.where(has_o, np.degrees(r.theta[idx, k]), np.nan),
        max_real_eig=mre)


# ---------------------------------------------------------------------------------------
# Losses
# ---------------------------------------------------------------------------------------

def scenario_losses(design, config: TuningConfig, scenarios: ScenarioSet,
                    eqs: EquilibriumSet | None = None, *, kind: str | None = None
                    ) -> Metrics:
    """Simulate every scenario with `design` and return the per-scenario `Metrics`
    (differentiable in `design`). `eqs`: the starting points of the penalty's Newton
    steps (from `equilibria`); `None` leaves the penalty out (and `w_stab = 0` too)."""
    traj = simulate_scenarios(design, config, scenarios, kind=kind)
    m = trajectory_metrics(traj, config)
    if eqs is not None and config.w_stab > 0:
        pen, _ = stability_penalty(design, config, scenarios, eqs, kind=kind)
    else:
        pen = jnp.zeros_like(m["pos_rms_deg"])
    loss = (config.w_pos * m["pos_rms_deg"] / config.theta_unit_deg
            + config.w_settle * m["settle_s"] / config.settle_unit_s
            + config.w_noise * m["noise_rad_s"] / config.noise_unit_rad_s
            + config.w_stab * pen)
    good = m["ok"] & jnp.isfinite(loss)
    loss = jnp.where(good, loss, config.diverged_loss)
    return Metrics(pos_rms_deg=m["pos_rms_deg"], theta_ss_deg=m["theta_ss_deg"],
                   settle_s=m["settle_s"], noise_rad_s=m["noise_rad_s"],
                   w_bias_rad_s=m["w_bias_rad_s"], stab_penalty=pen,
                   ok=m["ok"], loss=loss)


_REG_SHARP = 4.0  # sharpness of the regression hinge (per tolerance)


def regression_penalty(losses, reference, tol: float, weight: float):
    r"""The no-regression penalty (module docstring): $w\sum_j \mathrm{sp}_4((r_j -
    \tau/2)/\tau)$ with $r_j = (\ell_j - \ell_j^{ref})/\ell_j^{ref}$ the relative change
    of scenario $j$'s loss against the reference design's, $\tau$ = `tol` and $w$ =
    `weight` (loss units); $\mathrm{sp}_4(x) = \log(1 + e^{4x})/4$."""
    ref = jnp.maximum(jnp.abs(reference), _EPS)
    r = (losses - reference) / ref
    return weight * jnp.sum(jax.nn.softplus(_REG_SHARP * (r - 0.5 * tol) / tol)) / _REG_SHARP


def aggregate(losses, objective: str, temperature: float, *, reference=None,
              tol: float = 0.01, weight: float = 0.2):
    """`"average"`: mean; `"robust"`: log-mean-exp at `temperature` (smooth maximum);
    `"no_regression"`: the robust value plus `regression_penalty` against the per-scenario
    losses `reference` (of the baseline design; required) with `tol` and `weight`."""
    if objective == "average":
        return jnp.mean(losses)
    if objective in ("robust", "no_regression"):
        n = losses.shape[-1]
        value = temperature * (jax.scipy.special.logsumexp(losses / temperature, axis=-1)
                               - math.log(n))
        if objective == "robust":
            return value
        if reference is None:
            raise ValueError("the objective 'no_regression' needs the baseline's "
                             "per-scenario losses (`reference=...`).")
        return value + regression_penalty(losses, reference, tol, weight)
    raise ValueError(f"unknown objective {objective!r}; choose 'no_regression', 'robust' "
                     "or 'average'.")


def objective_value(losses, config: TuningConfig, reference=None, *,
                    objective: str | None = None):
    """`aggregate` with `config`'s objective (or `objective`), temperature, tolerance
    `regression_tol` and weight `w_regression`."""
    obj = config.objective if objective is None else objective
    return aggregate(losses, obj, config.temperature, reference=reference,
                     tol=config.regression_tol, weight=config.w_regression)


def report_objective(config: TuningConfig) -> str:
    """The aggregate reports compare designs with: the objective without the
    no-regression penalty ("robust" for "no_regression"), so that runs with either
    objective report the same quantity."""
    return "robust" if config.objective == "no_regression" else config.objective


def relative_change(losses, reference):
    """Relative change of each scenario's loss against `reference` (numpy)."""
    lb = np.asarray(reference, dtype=float)
    return (np.asarray(losses, dtype=float) - lb) / np.maximum(np.abs(lb), 1e-12)


def within_tolerance(losses, reference, tol: float) -> bool:
    """No scenario's loss exceeds its reference by more than `tol` (relative)."""
    return bool(np.all(relative_change(losses, reference) <= tol))


def loss(design, config: TuningConfig, scenarios: ScenarioSet,
         eqs: EquilibriumSet | None = None, *, objective: str | None = None,
         kind: str | None = None, reference=None):
    """The tuning objective of `design` on `scenarios`: `(value, Metrics)`.

    `eqs`: equilibria for the stability penalty (`equilibria(design, config, scenarios)`);
    pass them, or the penalty is left out. `reference`: the baseline's per-scenario
    losses (needed by the "no_regression" objective)."""
    m = scenario_losses(design, config, scenarios, eqs, kind=kind)
    return objective_value(m.loss, config, reference, objective=objective), m


def evaluate(design, config: TuningConfig, scenarios: ScenarioSet, *,
             objective: str | None = None, kind: str | None = None,
             chunk: int | None = None, reference=None):
    """`loss` with the penalty's equilibria computed for `design` first (not
    differentiable; use `loss` with `eqs` under `jax.grad`). Returns `(value, Metrics)`.

    `chunk`: evaluate the scenarios in batches of this size (the last one padded by
    repeating its final scenario), so that grids of other sizes reuse the compilation
    for `chunk` scenarios; the result is the same as one batch. `reference`: as in
    `loss`; without it the "no_regression" objective has nothing to compare with, and
    the value is the robust aggregate the reports use (`report_objective`).
    """
    if objective is None and reference is None:
        objective = report_objective(config)
    kind = config.observer if kind is None else kind  # the same programs as `feasibility`
    ms = []
    for part in _chunks(scenarios, chunk):
        eqs = equilibria(design, config, part, kind) if config.w_stab > 0 else None
        ms.append(_metrics_jit(design, config, part, eqs, kind))
    m = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a)[:scenarios.n], *ms)
    return objective_value(m.loss, config, reference, objective=objective), m


@eqx.filter_jit
def _metrics_jit(design, config, scenarios, eqs, kind):
    return scenario_losses(design, config, scenarios, eqs, kind=kind)


def residuals(design, config: TuningConfig, scenarios: ScenarioSet,
              eqs: EquilibriumSet | None = None, reference=None):
    """Residuals for least squares, `(r, Metrics)`: $r_j = \\sqrt{\\ell_j/n}$ (so
    $\\|r\\|^2$ is the average objective) for `objective="average"`, and the single
    residual $\\sqrt{L}$ of the smooth maximum $L$ for `"robust"` (with the regression
    penalty for `"no_regression"`; `reference` as in `loss`)."""
    m = scenario_losses(design, config, scenarios, eqs)
    if config.objective == "average":
        return _safe_sqrt(m.loss / m.loss.shape[0]), m
    return _safe_sqrt(objective_value(m.loss, config, reference))[None], m
