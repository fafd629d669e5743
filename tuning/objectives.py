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

**Stability/feasibility penalty.** At each scenario's operating point
$(\omega_0, i_0 = (0, i_q))$, with the observer's mismatched model and the design's gains
there, the error dynamics (11) (`pmsmjax.analysis.eso_rhs`, observer frame, fal
feedback for the ESO) have a designed (principal) equilibrium near $\tilde\theta = 0$ and
possibly others. Their locations come from `pmsmjax.analysis.eso_equilibria`
(bracketing and bisection: not differentiable, so they are computed under
`stop_gradient`) and are then refined by two Newton steps on the differentiable
right-hand side, which by the implicit-function theorem gives their exact first-order
dependence on the gains. For each equilibrium the Jacobian (37) is scaled as in the
analysis module (states by $|\psi_{a0}|$ and $|\omega_0|$, time by $|\omega_0|$), and its
characteristic polynomial $s^4 + c_1 s^3 + c_2 s^2 + c_3 s + c_4$
(`pmsmjax.analysis.charpoly`) gives the Routh-Hurwitz quantities
$m = (c_1, c_3, c_4, c_1c_2 - c_3, (c_1c_2-c_3)c_3 - c_1^2c_4)$, each divided by its
degree in a spectral scale $\rho$ (the mean root magnitude); all are positive iff the
equilibrium is stable (the exact test `routh_hurwitz` uses). The penalty $s_j$ sums

- designed equilibrium, Hurwitz with margin: $\sum_k \mathrm{sp}(-m_k)$ for the matrix
  shifted by the margin $\sigma = $ `hurwitz_margin` (rad/s), i.e. all poles left of
  $-\sigma$;
- every other equilibrium *not* stable (feasibility, Sec. IV):
  $\mathrm{sp}(\mathrm{smin}_k\, m_k)$;
- the slope bound $\kappa$ of the analysis' reduction (`reduction_kappa`) above 0.05:
  $\mathrm{sp}(1 - \kappa/0.05)$. The minimum-norm gains (25) always satisfy it;
  null-space components can violate it, and there the exact analysis does not apply
  (status -1), so the tuner is kept where feasibility can be certified;
- the designed poles resolvable at the sampling rate (`sampling_penalty`),

with $\mathrm{sp}(x) = \log(1 + e^{30x})/30$ and smin a smooth minimum. The penalty is
smooth and never NaN for a nondegenerate equilibrium, and its first two parts vanish
(in the limit) exactly where the exact test says feasible and Hurwitz. The report checks
feasibility with the exact (non-smooth) classification as well.

**Limits.** The analysis holds the gains fixed at the operating point, while the observer
schedules them with its own $\hat\omega$; and "no other stable equilibrium" does not
exclude other attractors (a slipping orbit: see the notebook). The simulated runs, with
their 30 deg initial error, are what checks the large-signal behaviour.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import pmsmjax as pj
from pmsmjax import jmul
from pmsmjax.analysis import charpoly, eso_equilibria, eso_rhs
from pmsmjax.observers import ESOGains, psi_a

from ._parametrise import GainSchedule
from .scenarios import (
    ScenarioSet,
    TuningConfig,
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
    """RMS error after the transient (deg), static error (deg), settling surrogate (s),
    speed-estimate noise and mean error (rad/s) and `ok` of a batched `Trajectory`."""
    t = traj.t
    th = traj.theta_err
    w_err = traj.w_m - traj.w_hat
    fin = jnp.isfinite(th) & jnp.isfinite(w_err)
    ok = traj.ok & jnp.all(fin, axis=-1)
    # keep non-finite samples out of the arithmetic (their gradient is dropped anyway)
    th = jnp.where(fin, th, 0.0)
    w_err = jnp.where(fin, w_err, 0.0)
    dt = config.T_s * config.save_every
    mask = (t >= config.t_transient - 0.5 * config.T_s).astype(th.dtype)
    nm = jnp.maximum(jnp.sum(mask, -1), 1.0)
    mean = lambda x: jnp.sum(x * mask, -1) / nm  # noqa: E731
    pos_ms = mean(th ** 2)
    th_ss = mean(th)
    dev = th - th_ss[..., None]
    th0 = math.radians(config.theta_err0_deg) or 1.0
    itse = jnp.sum(t * dev ** 2, -1) * dt
    w_mean = mean(w_err)
    w_var = mean((w_err - w_mean[..., None]) ** 2)
    return dict(pos_rms_deg=jnp.degrees(_safe_sqrt(pos_ms)), theta_ss_deg=jnp.degrees(th_ss),
                settle_s=_safe_sqrt(4.0 * itse / th0 ** 2), noise_rad_s=_safe_sqrt(w_var),
                w_bias_rad_s=w_mean, ok=ok)


# ---------------------------------------------------------------------------------------
# Stability and feasibility
# ---------------------------------------------------------------------------------------

def fal_parameters(kind: str, motor_hat: pj.PMSMParams):
    """`(a, eta)` of the feedback: ESO fal (0.5, 0.05 psi_f), linear (1, 1) otherwise."""
    if kind == "eso":
        return 0.5, 0.05 * motor_hat.psi_f
    return 1.0, 1.0


def design_gains(design, kind: str, motor_hat: pj.PMSMParams, w0, i0) -> ESOGains:
    """The gains of (15) at operating point `w0` (rad/s), `i0` (A) for the observer
    `kind`; the AFO's PI law (53) is the LESO with $g_2 = [0, -k_p]$, $g_3 = [0, -k_i]$
    (see `pmsmjax.AFOObserver`)."""
    g = design(motor_hat, w0, i0)
    if kind != "afo":
        return g
    k_p, k_i = design.pi(motor_hat, w0, i0)
    z = jnp.zeros_like(k_p)
    return ESOGains(G1=g.G1, g2=jnp.stack([z, -k_p]), g3=jnp.stack([z, -k_i]))


def _routh_margins(A):
    r"""Normalised Routh-Hurwitz quantities of a 4x4 matrix (all > 0 iff Hurwitz).

    Each is divided by its degree in a spectral scale $\rho$: the mean of
    $|c_1|/4$, $\sqrt{|c_2|/6}$, $\sqrt[3]{|c_3|/4}$, $\sqrt[4]{|c_4|}$ (each equals the
    root magnitude when all four roots are equal), so healthy margins are O(1)."""
    c = charpoly(A)
    c1, c2, c3, c4 = c[1], c[2], c[3], c[4]
    root = lambda x, k: (x * x + 1e-24) ** (0.5 / k)  # noqa: E731  (smooth |x|^(1/k))
    rho = 0.25 * (root(c1, 1) / 4 + root(c2 / 6, 2) + root(c3 / 4, 3) + root(c4, 4))
    rho = jnp.maximum(rho, 1e-6)
    d2 = c1 * c2 - c3
    d3 = d2 * c3 - c1 * c1 * c4
    return jnp.stack([c1 / rho, c3 / rho ** 3, c4 / rho ** 4, d2 / rho ** 3, d3 / rho ** 6])


def reduction_kappa(gains: ESOGains, w0):
    r"""$\kappa = 1 - u\cdot JG_1u/\omega_0$, $u = Jg_3^T/\|g_3\|$: the slope bound of
    the reduction `pmsmjax.analysis.eso_equilibria` relies on (it needs $\kappa > 0$,
    else it reports status -1). With the minimum-norm gains (25) $\kappa =
    \omega_1^2/\omega_0^2 > 0$; null-space components rotate $u$ and can make it
    negative when $\zeta_1 > 1$."""
    g3 = gains.g3
    u = jmul(g3) / jnp.sqrt(jnp.sum(g3 ** 2) + 1e-300)
    return 1.0 - jnp.dot(u, jmul(gains.G1 @ u)) / w0


_KAPPA_MIN = 0.05
_POLE_TS_MAX = 0.8  # fastest designed pole times T_s


def sampling_penalty(design, kind: str, w0, T_s):
    r"""Keep the designed poles resolvable at the sampling rate: with
    $p(\zeta, \omega) = \omega(\zeta + \sqrt{\zeta^2 + 1})$ (a smooth upper bound of the
    faster pole of $s^2 + 2\zeta\omega s + \omega^2$), the penalty is
    $\mathrm{sp}((p\,T_s - 0.8)/0.2)$ for the flux and the speed/angle poles at `w0`.
    The discrete observer integrates the speed and angle by forward Euler, which turns
    unstable for poles beyond about $2/T_s$. Defined for a `GainSchedule`; other designs
    give 0."""
    if not isinstance(design, GainSchedule):
        return jnp.zeros(())
    v = design.values(w0 / design.w_rated)
    p = lambda z, w: w * (z + jnp.sqrt(z * z + 1.0))  # noqa: E731
    del kind  # the same poles for ESO, LESO and AFO
    flux = p(v["zeta1"], v["ratio"] * jnp.abs(w0))
    speed = p(v["zeta2"], v["w2"])
    return (_sp((flux * T_s - _POLE_TS_MAX) / 0.2) + _sp((speed * T_s - _POLE_TS_MAX) / 0.2))


def _sp(x):
    return jax.nn.softplus(_SHARP * x) / _SHARP


def _smin(m, tau=0.05):
    return -tau * jax.scipy.special.logsumexp(-m / tau)


class EquilibriumSet(eqx.Module):
    """Equilibria of the error dynamics (11) at every scenario's operating point
    (`pmsmjax.analysis.eso_equilibria`, leading axis: scenario, then `K` slots).

    - `x`: states `(n, K, 4)` (V s, V s, rad, rad/s), 0 in invalid slots; `theta` (rad).
    - `valid`, `stable`: `(n, K)`; `principal`: index of the designed equilibrium `(n,)`.
    - `status`: 0 ok, -1 the analysis failed or does not apply.
    """

    x: jnp.ndarray
    theta: jnp.ndarray
    valid: jnp.ndarray
    stable: jnp.ndarray
    principal: jnp.ndarray
    status: jnp.ndarray


def _point(config: TuningConfig, drive, kind, design, k_d, k_q, speed_pu, load_pu):
    """Operating point, observer model, fal parameters and gains of one scenario."""
    mh = observer_motor(drive, k_d, k_q)
    w0 = speed_pu * float(drive.w_rated)
    i0 = operating_current(drive, load_pu)
    a, eta = fal_parameters(kind, mh)
    gains = design_gains(design, kind, mh, w0, i0)
    return w0, i0, drive.three_phase_motor, mh, a, eta, gains


@eqx.filter_jit
def equilibria(design, config: TuningConfig, scenarios: ScenarioSet, kind: str | None = None
               ) -> EquilibriumSet:
    """Every equilibrium of the error dynamics at each scenario's operating point, for the
    gains of `design` (bracketing and bisection: not differentiable; see
    `stability_penalty` for how the loss uses them)."""
    drive = config.drive()
    kind = config.observer if kind is None else kind

    def one(k_d, k_q, speed_pu, load_pu):
        w0, i0, motor, mh, a, eta, gains = _point(config, drive, kind, design, k_d, k_q,
                                                  speed_pu, load_pu)
        eq = eso_equilibria(w0, i0, gains, motor, mh, a=a, eta=eta, n_grid=config.n_grid,
                            max_roots=8 if kind == "eso" else 4)
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
        w0, i0, motor, mh, a, eta, gains = _point(config, drive, kind, design, k_d, k_q,
                                                  speed_pu, load_pu)
        pn = jnp.sqrt(jnp.sum(psi_a(mh, i0) ** 2))
        d = jnp.stack([1 / pn, 1 / pn, jnp.ones_like(pn), 1 / jnp.abs(w0)])

        def rhs(x):
            return eso_rhs(x, w0, i0, gains, motor, mh, a, eta)

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
        m_shift = jax.vmap(_routh_margins)(A + sigma * jnp.eye(4))
        m = jax.vmap(_routh_margins)(A)
        pen_p = jnp.sum(_sp(-m_shift), -1)
        pen_o = _sp(jax.vmap(_smin)(m))
        # the designed equilibrium: if the search failed, use the origin
        A0 = scaled_jac(refine(jnp.zeros(4, A.dtype)))
        pen_0 = jnp.sum(_sp(-_routh_margins(A0 + sigma * jnp.eye(4))))
        has_p = jnp.any(principal)
        pen = jnp.where(has_p, jnp.sum(jnp.where(principal, pen_p, 0.0)), pen_0)
        pen = pen + jnp.sum(jnp.where(valid & ~principal, pen_o, 0.0))
        pen = pen + _sp(1.0 - reduction_kappa(gains, w0) / _KAPPA_MIN)
        pen = pen + sampling_penalty(design, kind, w0, config.T_s)
        margin = jnp.where(has_p, jnp.sum(jnp.where(principal[:, None], m, 0.0), 0),
                           _routh_margins(A0))
        pen = jnp.where(jnp.isfinite(pen), pen, 10.0)
        return pen, _smin(margin)

    return jax.vmap(one)(scenarios.k_d, scenarios.k_q, scenarios.speed_pu,
                         scenarios.load_pu, eqs)


@eqx.filter_jit
def _principal_max_eig(design, config, scenarios, eqs, kind):
    drive = config.drive()

    def one(k_d, k_q, speed_pu, load_pu, eq):
        w0, i0, motor, mh, a, eta, gains = _point(config, drive, kind, design, k_d, k_q,
                                                  speed_pu, load_pu)
        A = jax.jacfwd(lambda x: eso_rhs(x, w0, i0, gains, motor, mh, a, eta))(
            eq.x[eq.principal])
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
    """Exact (non-smooth) check per scenario, from `pmsmjax.analysis.eso_equilibria`.

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


def aggregate(losses, objective: str, temperature: float):
    """`"average"`: mean; `"robust"`: log-mean-exp at `temperature` (smooth maximum)."""
    if objective == "average":
        return jnp.mean(losses)
    if objective == "robust":
        n = losses.shape[-1]
        return temperature * (jax.scipy.special.logsumexp(losses / temperature, axis=-1)
                              - math.log(n))
    raise ValueError(f"unknown objective {objective!r}; choose 'robust' or 'average'.")


def loss(design, config: TuningConfig, scenarios: ScenarioSet,
         eqs: EquilibriumSet | None = None, *, objective: str | None = None,
         kind: str | None = None):
    """The tuning objective of `design` on `scenarios`: `(value, Metrics)`.

    `eqs`: equilibria for the stability penalty (`equilibria(design, config, scenarios)`);
    pass them, or the penalty is left out."""
    m = scenario_losses(design, config, scenarios, eqs, kind=kind)
    obj = config.objective if objective is None else objective
    return aggregate(m.loss, obj, config.temperature), m


def evaluate(design, config: TuningConfig, scenarios: ScenarioSet, *,
             objective: str | None = None, kind: str | None = None,
             chunk: int | None = None):
    """`loss` with the penalty's equilibria computed for `design` first (not
    differentiable; use `loss` with `eqs` under `jax.grad`). Returns `(value, Metrics)`.

    `chunk`: evaluate the scenarios in batches of this size (the last one padded by
    repeating its final scenario), so that grids of other sizes reuse the compilation
    for `chunk` scenarios; the result is the same as one batch.
    """
    obj = config.objective if objective is None else objective
    ms = []
    for part in _chunks(scenarios, chunk):
        eqs = equilibria(design, config, part, kind) if config.w_stab > 0 else None
        ms.append(_metrics_jit(design, config, part, eqs, kind))
    m = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a)[:scenarios.n], *ms)
    return aggregate(m.loss, obj, config.temperature), m


@eqx.filter_jit
def _metrics_jit(design, config, scenarios, eqs, kind):
    return scenario_losses(design, config, scenarios, eqs, kind=kind)


def residuals(design, config: TuningConfig, scenarios: ScenarioSet,
              eqs: EquilibriumSet | None = None):
    """Residuals for least squares, `(r, Metrics)`: $r_j = \\sqrt{\\ell_j/n}$ (so
    $\\|r\\|^2$ is the average objective) for `objective="average"`, and the single
    residual $\\sqrt{L}$ of the smooth maximum $L$ for `"robust"`."""
    m = scenario_losses(design, config, scenarios, eqs)
    if config.objective == "average":
        return _safe_sqrt(m.loss / m.loss.shape[0]), m
    return _safe_sqrt(aggregate(m.loss, "robust", config.temperature))[None], m
