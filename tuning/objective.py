r"""Per-run metrics -> per-run losses -> a tail-risk aggregate with per-metric constraints.

**Metrics of one run** (`run_metrics`): the library's run metrics (`pmsmjax.run_metrics`,
the one definition the comparison job uses too; $\tilde\theta$ the wrapped angle error,
true minus estimate, in deg; $\tilde\omega = \omega - \hat\omega$) and two of the tuner's
own, made of the same errors (`pmsmjax.run_errors`):

- `rms_deg`: RMS of $\tilde\theta$ over the whole run (ramps, reversal, load step);
- `peak_deg`: a smooth peak of $|\tilde\theta|$, the $p$-norm mean
  $(\mathrm{mean}|\tilde\theta|^p)^{1/p}$ with $p = 8$ (differentiable, within a
  few per cent of the maximum for a transient that lasts a few per cent of the run);
- `static_deg`: mean of $\tilde\theta$ over the static window (`pmsmjax.static_window`:
  the last `pmsmjax.STATIC_WINDOW` = 20 % of the run, by time);
- `noise_rad_s`: standard deviation of $\tilde\omega$ over the static window
  (electrical);
- `lost_lock`: the run lost lock, by the library's one definition (`pmsmjax.lock_status`
  with `start_locked`: the mean $|\tilde\theta|$ over any 10 ms of the run above
  `lock_deg`, the observer having started on the true angle, or the run diverged);
  `out_of_lock`: the fraction of samples above `lock_deg`, smooth (a logistic of width
  2 deg), which is what the objective differentiates.

**Loss of a run**: $L = \mathrm{rms}/\theta_u + w_{peak}\,\mathrm{peak}/\theta_{pk}
+ w_{noise}\,\sigma_\omega/\sigma_u$. A run that diverged or produced a non-finite sample
gets the loss of a run that is wrong by 180 deg everywhere with no gradient (the
non-finite samples are replaced before any arithmetic, so no NaN reaches a gradient). A
run that merely loses lock stays finite (the wrapped error is bounded) and enters
through its large RMS and peak errors, its `out_of_lock` fraction (below) and the
constraint.

**Aggregate** (`objective`), relative to a reference design (the paper's) run on the same
scenarios, $r_i = L_i / L_{ref,i}$:

$$J = \tfrac12\,\overline{r} + \tfrac12\,\mathrm{CVaR}_\beta(r)
 + w_c\sum_i\mathrm{softplus}_k(\mathrm{rms}_i/\mathrm{rms}_{ref,i} - 1 - tol/2)
 + w_c\sum_i[\mathrm{ref}_i\ \mathrm{in\ lock}]\ \mathrm{out\_of\_lock}_i$$

$\mathrm{CVaR}_\beta$ is the mean of the worst fraction $\beta$ (`cvar_fraction`) of the
ratios: the tail that a mean hides, but unlike a maximum it does not hang the whole
objective on one run's noise. The mean keeps every run pulling (the target is to improve
most runs, not only the worst). Ratios make runs of very different difficulty
(0.1 p.u. with wrong $R_s$ and 0.8 p.u. matched) count alike. The two constraint terms
are the no-regression rule per metric: no run's RMS angle error worse than the
reference's by more than half of `regression_tol` (half: a margin for the runs the tuner
never sees), and no run out of lock where the reference holds it; they are sums, not
means, so that one violating run costs as much in a large batch as in a small one;
`softplus_k` is a softplus of sharpness k = 50 (zero well inside, linear outside).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import pmsmjax as pj

from .problem import TuningProblem


#: The p of the smooth peak.
PEAK_P = 8
#: The training constraint holds the RMS error within this fraction of the tolerance
#: (a margin for runs the tuner does not see).
MARGIN = 0.5
#: A run counts as better (worse) when its loss is lower (higher) than the reference's
#: by more than this (relative): 0.1 %.
BETTER = 1e-3
#: Sharpness of the constraint's softplus.
SHARPNESS = 50.0


class Metrics(eqx.Module):
    """Per-run metrics (arrays with the batch shape; see the module docstring)."""

    rms_deg: jnp.ndarray
    peak_deg: jnp.ndarray
    static_deg: jnp.ndarray
    noise_rad_s: jnp.ndarray
    out_of_lock: jnp.ndarray
    lost_lock: jnp.ndarray
    ok: jnp.ndarray
    loss: jnp.ndarray
    #: when the run lost lock (s; `pmsmjax.run_metrics`; NaN if it kept lock; None where
    #: the metrics were not computed from runs)
    t_lost: jnp.ndarray | None = None


def run_metrics(traj: pj.Trajectory, problem: TuningProblem) -> Metrics:
    """`Metrics` of a (batched) trajectory (samples on the last axis)."""
    base = pj.run_metrics(traj, lock_deg=problem.lock_deg)
    th, _, ok = pj.run_errors(traj)
    a = jnp.abs(th) + 1e-6
    peak = jnp.mean(a ** PEAK_P, axis=-1) ** (1.0 / PEAK_P)
    out = jnp.mean(jax.nn.sigmoid((jnp.abs(th) - problem.lock_deg) / 2.0), axis=-1)
    rms, noise = base["rms_deg"], base["noise_rad_s"]
    loss = (rms / problem.theta_unit_deg + problem.w_peak * peak / problem.peak_unit_deg
            + problem.w_noise * noise / problem.noise_unit_rad_s)
    worst = (180.0 / problem.theta_unit_deg + problem.w_peak * 180.0 /
             problem.peak_unit_deg)
    loss = jnp.where(ok, loss, jax.lax.stop_gradient(jnp.maximum(loss, worst)))
    return Metrics(rms_deg=rms, peak_deg=peak, static_deg=base["static_deg"],
                   noise_rad_s=noise, out_of_lock=out, lost_lock=base["lost_lock"], ok=ok,
                   loss=loss, t_lost=base["t_lost"])


def cvar(r, fraction: float):
    """Mean of the largest `ceil(fraction * n)` entries of `r` (last axis)."""
    n = r.shape[-1]
    k = max(1, int(-(-fraction * n // 1)))
    return jnp.mean(jax.lax.top_k(r, k)[0], axis=-1)


def _softplus(x, k=SHARPNESS):
    return jax.nn.softplus(k * x) / k


def objective(m: Metrics, ref: Metrics, problem: TuningProblem):
    """The scalar objective $J$ of metrics `m` against the reference `ref` (same runs)
    and its parts `{"mean", "cvar", "rms_constraint", "lock_constraint"}`."""
    r = m.loss / ref.loss
    rms_excess = m.rms_deg / ref.rms_deg - 1.0 - MARGIN * problem.regression_tol
    held = (~ref.lost_lock).astype(r.dtype)
    parts = {"mean": jnp.mean(r, axis=-1), "cvar": cvar(r, problem.cvar_fraction),
             "rms_constraint": jnp.sum(_softplus(rms_excess), axis=-1),
             "lock_constraint": jnp.sum(held * m.out_of_lock, axis=-1)}
    J = (0.5 * parts["mean"] + 0.5 * parts["cvar"]
         + problem.w_constraint * (parts["rms_constraint"] + parts["lock_constraint"]))
    return J, parts


#: The accounting vocabulary: one definition per key, the same words in summary.json
#: (`accounting.SPLIT`), the console, the figures and the docs. "The paper design" is the
#: reference run on the same runs.
VOCABULARY = {
    "n": "runs compared (the same runs for both designs)",
    "better": "runs whose loss is lower than the paper design's by more than 0.1 % "
              "(relative; a smaller change is a tie, and so is a run both designs lose "
              "lock in)",
    "worse": "runs whose loss is higher than the paper design's by more than 0.1 % "
             "(relative; a run both designs lose lock in is a tie)",
    "fraction_better": "better / n",
    "worst_rms_change_pct": "the largest change of a run's RMS angle error against the "
                            "paper design's on the same run, over the runs at least one "
                            "of them holds in lock (%, positive: worse)",
    "new_lost_lock": "runs that lose lock where the paper design holds it",
    "beyond_limit": "validation runs the low-speed rule, fixed before tuning, puts beyond "
                    "the observer's class (a sensored drive turns slower there than the "
                    "class's limit); every other count is over the remaining runs",
    "unloaded": "validation runs, among the n, judged without their load step: the "
                "low-speed rule's twin of a run whose load step alone takes a sensored "
                "drive below the class's limit",
}
#: The reference's name in the reports (the verdict's baseline).
BASELINE = "the paper's design"
#: Keys kept one release for the readers of an older summary.json: old key -> the key
#: that replaces it (`improved` counted a loss lower by more than the tolerance, not
#: 0.1 %).
DEPRECATED_KEYS = {"improved": "better", "improved_frac": "fraction_better"}


def accounting(m: Metrics, ref: Metrics, tol: float, beyond=None, unloaded=None) -> dict:
    """Per-metric comparison of `m` with `ref` over the same runs (plain numbers): first
    the RMS angle error (deg, mean over the runs: `mean_rms_deg`, and the reference's
    `mean_rms_deg_reference`), then the keys of `VOCABULARY` (`better`, `worse`: loss
    lower / higher by more than `BETTER`, 0.1 %, a change at the level of rounding is a
    tie; `fraction_better`; `worst_rms_change_pct`; `new_lost_lock`), then the
    details: the tolerance (%), runs whose RMS angle error is worse by more than `tol`
    (relative), the worst run's index, lock lost by each design, `lost_by_both`, the
    median loss change (%), and the `DEPRECATED_KEYS` (`improved`: loss lower by more
    than `tol`; `improved_frac` = `fraction_better`).

    **Runs both designs lose lock in** (`lost_by_both`, `judged`) are ties: neither
    `better` nor `worse`, and outside `worst_rms_change_pct` and `rms_worse_than_tol`.
    After a lock loss the angle error wanders over the whole circle, and its RMS is
    chaotic: the paper's own design with its gains changed by 1e-9 moves it by several per
    cent (the rule's floor, `tuning.pipeline`). A run only one design loses is judged:
    `new_lost_lock` where the paper's design holds it, `better` (a loss far lower) where
    the tuned design holds it. Where every run is lost by both, `worst_rms_change_pct` is
    0 and `worst_run` None.

    `beyond`: a boolean per run, the runs the low-speed rule puts beyond the observer's
    class (`tuning.low_speed_runs`, decided before tuning): every count above is over the
    other runs (`n` of them; `worst_run` indexes all runs), and `beyond_limit`,
    `lost_lock_beyond`, `lost_lock_beyond_reference` count those apart. None: no run.
    `unloaded`: a boolean per run, the runs the rule judges without their load step
    (`tuning.apply_low_speed_rule`); `unloaded` counts those among the `n`. None: no run."""
    n_all = np.asarray(m.loss).size
    out = np.zeros(n_all, bool) if beyond is None else np.asarray(beyond, bool)
    if out.shape != (n_all,):
        raise ValueError(f"`accounting(beyond=...)` must hold one bool per run ({n_all}); "
                         f"got shape {out.shape}.")
    twin = np.zeros(n_all, bool) if unloaded is None else np.asarray(unloaded, bool)
    if twin.shape != (n_all,):
        raise ValueError(f"`accounting(unloaded=...)` must hold one bool per run ({n_all}); "
                         f"got shape {twin.shape}.")
    keep = np.nonzero(~out)[0]
    if not keep.size:
        raise ValueError("`accounting`: the low-speed rule leaves no run to compare (every "
                         "run is beyond the observer's class).")
    loss, loss_r = np.asarray(m.loss)[keep], np.asarray(ref.loss)[keep]
    rms, rms_r = np.asarray(m.rms_deg)[keep], np.asarray(ref.rms_deg)[keep]
    lost_all, lost_r_all = np.asarray(m.lost_lock), np.asarray(ref.lost_lock)
    lost, lost_r = lost_all[keep], lost_r_all[keep]
    rel = loss / loss_r - 1.0
    ok = judged(lost, lost_r)
    rms_rel = np.where(ok, rms / rms_r - 1.0, -np.inf)
    worst = int(np.argmax(rms_rel)) if ok.any() else None
    better = int(np.sum(ok & (rel < -BETTER)))
    n = int(keep.size)
    return {"mean_rms_deg": float(np.mean(rms)),
            "mean_rms_deg_reference": float(np.mean(rms_r)),
            "n": n, "better": better, "worse": int(np.sum(ok & (rel > BETTER))),
            "fraction_better": better / n,
            "worst_rms_change_pct": 0.0 if worst is None else float(100.0 * rms_rel[worst]),
            "new_lost_lock": int(np.sum(lost & ~lost_r)),
            "tolerance_pct": 100.0 * tol,
            "rms_worse_than_tol": int(np.sum(rms_rel > tol)),
            "worst_run": None if worst is None else int(keep[worst]),
            "lost_lock": int(np.sum(lost)), "lost_lock_reference": int(np.sum(lost_r)),
            "lost_by_both": int(np.sum(~ok)),
            "median_loss_change_pct": float(100.0 * np.median(rel)),
            "beyond_limit": int(np.sum(out)),
            "unloaded": int(np.sum(twin & ~out)),
            "lost_lock_beyond": int(np.sum(lost_all[out])),
            "lost_lock_beyond_reference": int(np.sum(lost_r_all[out])),
            # deprecated (DEPRECATED_KEYS), kept one release
            "improved": int(np.sum(ok & (rel < -tol))), "improved_frac": better / n}


def judged(lost, lost_reference):
    """Per run, whether the accounting judges it: not lost by both designs (`accounting`:
    a run both lose is a tie). Boolean arrays of the runs' `lost_lock`."""
    return ~(np.asarray(lost, bool) & np.asarray(lost_reference, bool))


def holds(acc: dict, min_frac: float = 0.75) -> tuple[bool, list[str]]:
    """The validation rule: better than the reference in at least `min_frac` of the
    runs, no run's RMS angle error worse by more than the tolerance, no lock lost that
    the reference holds. Returns `(holds, reasons it does not)`."""
    why = []
    if acc["better"] < min_frac * acc["n"]:
        why.append(f"better in {acc['better']} of {acc['n']} runs (< {100 * min_frac:g} %)")
    if acc["rms_worse_than_tol"]:
        why.append(f"{acc['rms_worse_than_tol']} runs with the RMS angle error worse by more "
                   f"than {acc['tolerance_pct']:g} % (worst {acc['worst_rms_change_pct']:+.1f}"
                   f" %)")
    if acc["new_lost_lock"]:
        why.append(f"{acc['new_lost_lock']} runs lose lock that the reference holds")
    return not why, why


__all__ = ["BASELINE", "BETTER", "DEPRECATED_KEYS", "VOCABULARY", "Metrics", "accounting",
           "cvar", "holds", "judged", "objective", "run_metrics"]
