r"""Validation of a tuned design on scenarios the tuner never saw.

The training and held-out scenarios (`tuning.scenarios`) hold the rotor speed with a
load machine and control the current directly, so that the simulated operating point is
exactly the one the equilibrium analysis sees. A user's drive is different: the speed
is controlled through the observer's own estimate, the reference ramps, the load steps,
and every machine parameter of the observer's model may be wrong. The validation set is
such runs, at speeds between and beyond the training speeds, in both directions:

- **closed loop, sensorless, speed controlled**: `pmsmjax.FOC` (the configuration's
  controller) with its speed loop fed by the observer's $\hat\omega$ and the current
  control in the observer's frame $\hat\theta$; the rotor's mechanical equation is
  integrated (`Scenario(w_m_ref=...)`, nothing imposed);
- **speed ramp**: the drive runs at `val_start_frac` x the final speed (observer started
  on the true state), the reference ramps to the final speed over
  $[0.1, 0.3]\,t_{end}$;
- **load step**: 0 -> `val_load_pu` x rated torque at $0.6\,t_{end}$;
- **speeds** `val_speeds_pu` with both signs (default 0.1, 0.4, 0.5 and 0.8 p.u.: below,
  between and off the training speeds 0.2, 0.6, 1.0);
- **observer-model mismatch** in $L_d$, $L_q$, $R_s$, $\psi_f$ and the **current-noise**
  level, one *case* $(k_d, k_q, k_R, k_\psi, k_{noise})$ per row of `val_cases`
  (observer value / plant value; `k_noise` scales `noise_std`), every case at every speed;
  other noise keys than training and held-out.

**Metrics** per run (`Metrics`, the same fields as for training): the RMS angle error
over the whole run (deg; the observer starts on the true angle, so this is the error the
ramp, the load step, the mismatch and the noise cause), the static error (deg) and the
speed-estimate noise (rad/s: standard deviation of $\omega - \hat\omega$), both over the
last 20 % of the run, after the load step (over the whole run the speed estimate's lag
during the ramp would count as noise; `w_bias_rad_s` is the mean over the whole run),
and the validation loss
$w_{pos}\,p/\theta_u + w_{noise}\,\sigma/\sigma_u$ (the training loss without the
settling surrogate, which measures the decay of an initial angle error these runs do not
have, and without the stability penalty, an analysis at a fixed operating point). A run
that diverged gets `diverged_loss`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

import pmsmjax as pj
from pmsmjax._simulate import scale_motor

from .objectives import Metrics
from .scenarios import TuningConfig, make_observer


#: Fraction of the run at which the ramp starts and ends, and the load steps.
RAMP = (0.1, 0.3)
LOAD_STEP = 0.6
#: The static error is the mean angle error over this last fraction of the run.
STATIC_WINDOW = 0.2
#: Offset of the validation noise keys from `config.seed` (training: +0, held-out: +10000).
SEED_OFFSET = 20_000

_CASE_FIELDS = ("k_d", "k_q", "k_R", "k_psi", "k_noise")


class ValidationSet(eqx.Module):
    """A flat batch of validation runs (one entry per run).

    - `speed_pu`: final speed reference (p.u. of rated, signed); `start_pu`: the speed
      the run starts at (p.u.).
    - `load_pu`: the load after the step (p.u. of rated torque, braking: opposite to the
      rotation).
    - `k_d`, `k_q`, `k_R`, `k_psi`: observer model / plant of $L_d$, $L_q$, $R_s$,
      $\\psi_f$ (-).
    - `k_noise`: current-noise std in units of `config.noise_std` (-).
    - `keys`: PRNG key of each run's current noise.
    """

    speed_pu: jnp.ndarray
    start_pu: jnp.ndarray
    load_pu: jnp.ndarray
    k_d: jnp.ndarray
    k_q: jnp.ndarray
    k_R: jnp.ndarray
    k_psi: jnp.ndarray
    k_noise: jnp.ndarray
    keys: jnp.ndarray

    @property
    def n(self) -> int:
        return int(np.shape(self.speed_pu)[0])

    def table(self) -> list[dict]:
        """One dict per run (plain floats), for reports."""
        cols = {k: np.asarray(getattr(self, k)) for k in (
            "speed_pu", "start_pu", "load_pu", *_CASE_FIELDS)}
        return [{k: float(v[j]) for k, v in cols.items()} for j in range(self.n)]


def validation_scenarios(config: TuningConfig) -> ValidationSet:
    """Every case of `config.val_cases` at every speed of `config.val_speeds_pu`, both
    signs (noise keys from `config.seed + SEED_OFFSET`)."""
    speeds = [s for v in config.val_speeds_pu for s in (v, -v)]
    cases = np.asarray(config.val_cases, dtype=float).reshape(-1, len(_CASE_FIELDS))
    rows = np.array([(s, *c) for c in cases for s in speeds], dtype=float)
    n = rows.shape[0]
    base = jr.PRNGKey(config.seed + SEED_OFFSET)
    keys = jax.vmap(lambda j: jr.fold_in(base, j))(jnp.arange(n))
    sp = rows[:, 0]
    return ValidationSet(
        speed_pu=jnp.asarray(sp), start_pu=jnp.asarray(config.val_start_frac * sp),
        load_pu=jnp.full(n, float(config.val_load_pu)),
        **{k: jnp.asarray(rows[:, 1 + i]) for i, k in enumerate(_CASE_FIELDS)},
        keys=keys)


def validation_scenario(config: TuningConfig, speed_pu, start_pu, load_pu) -> pj.Scenario:
    """The `pmsmjax.Scenario` of one validation run: speed reference ramp from
    `start_pu` to `speed_pu` over `RAMP` x `val_t_end`, braking load step to `load_pu` at
    `LOAD_STEP` x `val_t_end` (speed controlled: no speed imposed)."""
    drive = config.drive()
    w_r = float(drive.w_rated)
    t_end = config.val_t_end
    t0, t1 = (round(f * t_end / config.T_s) * config.T_s for f in RAMP)
    t_step = round(LOAD_STEP * t_end / config.T_s) * config.T_s
    tau = load_pu * float(drive.tau_rated) * jnp.sign(speed_pu)
    return pj.Scenario(t_end=t_end,
                       w_m_ref=pj.Profile([t0, t1], jnp.stack([start_pu * w_r,
                                                               speed_pu * w_r])),
                       tau_L=pj.Profile([t_step, t_step], jnp.stack([0.0 * tau, tau])))


def observer_model(drive: pj.Drive, k_d, k_q, k_R, k_psi) -> pj.PMSMParams:
    """The observer's machine model: the drive's with $L_d$, $L_q$, $R_s$, $\\psi_f$
    scaled by the factors (observer value / plant value)."""
    return scale_motor(drive.three_phase_motor,
                       {"L_d": k_d, "L_q": k_q, "R_s": k_R, "psi_f": k_psi})


def simulate_validation(design, config: TuningConfig, vset: ValidationSet, *,
                        kind: str | None = None, save_every: int | None = None
                        ) -> pj.Trajectory:
    """Run every validation scenario with the observer `config.observer` (or `kind`) and
    `design` (as `tuning.simulate_scenarios`; vmapped, `throw=False`)."""
    drive = config.drive()
    foc = config.controller()
    kind = config.observer if kind is None else kind
    save_every = config.save_every if save_every is None else save_every
    w_r = float(drive.w_rated)
    noisy = config.noise_std > 0

    def one(speed_pu, start_pu, load_pu, k_d, k_q, k_R, k_psi, k_noise, key):
        obs = make_observer(kind, drive, design,
                            motor=observer_model(drive, k_d, k_q, k_R, k_psi))
        sc = validation_scenario(config, speed_pu, start_pu, load_pu)
        sensing = pj.Sensing(noise_std=config.noise_std * k_noise)
        return pj.simulate(drive, foc, obs, sc, T_s=config.T_s, sensing=sensing,
                           key=key if noisy else None, theta0=0.0, w_m0=start_pu * w_r,
                           theta_hat0=0.0, save_every=save_every, throw=False)

    return jax.vmap(one)(vset.speed_pu, vset.start_pu, vset.load_pu, vset.k_d, vset.k_q,
                         vset.k_R, vset.k_psi, vset.k_noise, vset.keys)


def validation_metrics(traj: pj.Trajectory, config: TuningConfig) -> Metrics:
    """Per-run `Metrics` of a batch of validation runs (see the module docstring)."""
    whole = pj.trajectory_metrics(traj, t_transient=0.0, T_s=config.T_s,
                                  save_every=config.save_every, theta_err0=1.0)
    last = pj.trajectory_metrics(traj, t_transient=(1 - STATIC_WINDOW) * config.val_t_end,
                                 T_s=config.T_s, save_every=config.save_every,
                                 theta_err0=1.0)
    loss = (config.w_pos * whole["pos_rms_deg"] / config.theta_unit_deg
            + config.w_noise * last["noise_rad_s"] / config.noise_unit_rad_s)
    good = whole["ok"] & jnp.isfinite(loss)
    loss = jnp.where(good, loss, config.diverged_loss)
    return Metrics(pos_rms_deg=whole["pos_rms_deg"], theta_ss_deg=last["theta_ss_deg"],
                   settle_s=whole["settle_s"], noise_rad_s=last["noise_rad_s"],
                   w_bias_rad_s=whole["w_bias_rad_s"],
                   stab_penalty=jnp.zeros_like(loss), ok=whole["ok"], loss=loss)


@eqx.filter_jit
def _validate_jit(design, config, vset, kind):
    return validation_metrics(simulate_validation(design, config, vset, kind=kind), config)


def validate(design, config: TuningConfig, vset: ValidationSet | None = None, *,
             kind: str | None = None) -> Metrics:
    """`Metrics` of `design` on the validation set (`validation_scenarios(config)` unless
    `vset` is given)."""
    vset = validation_scenarios(config) if vset is None else vset
    return _validate_jit(design, config, vset, kind)


__all__ = ["ValidationSet", "observer_model", "simulate_validation",
           "validate", "validation_metrics", "validation_scenario", "validation_scenarios"]
