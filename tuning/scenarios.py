r"""The tuning problem: configuration, inductance-mismatch grids and the batch of runs.

Every scenario is one sensorless closed-loop run at a constant operating point, the
setting of zhang2022 Secs. III-IV:

- the rotor speed $\omega_0$ is held by a load machine (`Scenario(w_m_imposed=...)`) and
  the drive is current-controlled in the estimator frame with $i_d = 0$ and the
  $i_q$ of the load torque, so the operating point $(\omega_0, i_0)$ of the equilibrium
  analysis is exactly the one simulated (no speed-loop transient mixes in);
- the observer starts with an angle error (`theta_err0_deg`, true minus estimate) and the
  true speed;
- the observer's machine model has $\hat L_d = k_d L_d$, $\hat L_q = k_q L_q$ (saturation,
  a wrong datasheet), with $(k_d, k_q)$ on a grid; the plant and the current controller
  keep the true values, so only the observer is mismatched;
- the sampled currents carry white noise (`Sensing(noise_std)`) drawn from a fixed key
  per scenario, so a configuration and a seed define every run exactly.

The held-out grid uses mismatch values disjoint from the training grid (the midpoints
of a regular grid over the same range) and other noise keys.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

import pmsmjax as pj

from ._parametrise import TUNABLE, Bounds, GainSchedule, zhang38_schedule


OBSERVERS = ("eso", "leso", "afo")
OBJECTIVES = ("robust", "average")
OPTIMISERS = ("adam", "bfgs", "lm")


def _tuple(x):
    return tuple(float(v) for v in np.asarray(x, dtype=float).reshape(-1))


@dataclasses.dataclass(frozen=True)
class TuningConfig:
    """Everything that defines a tuning run (validated on construction).

    **Problem**

    - `motor`: preset name (`pmsmjax.PRESET_NAMES`).
    - `observer`: `"eso"` (fal feedback, `a = 0.5`, `eta = 0.05 psi_f`), `"leso"` or
      `"afo"`.
    - `T_s` (s), `t_end` (s): sampling period and run length.
    - `t_transient` (s): the position-error energy and the speed-estimate noise are
      measured on `[t_transient, t_end)`.
    - `theta_err0_deg`: initial angle error (deg, true minus estimate).
    - `noise_std`: current-sensor noise (A per component); 0 = none.
    - `speeds_pu`, `loads_pu`: operating speeds (p.u. of rated, nonzero) and loads (p.u.
      of rated torque, carried by `i_q` with `i_d = 0`).
    - `mismatch`: `(lo, hi)` range of $\\hat L/L$; `n_mismatch` values per axis on the
      training grid (product over $k_d$, $k_q$), or `mismatch_values` explicitly.
    - `n_heldout`: values per axis of the held-out grid (midpoints, disjoint).
    - `nodes_pu`: speed nodes of the `GainSchedule` (p.u.).
    - `w2_paper_hz`: bandwidth of the paper's design (38)/(25) used as baseline and
      starting point (Hz).
    - `bounds`: the `Bounds` (or a dict of its arguments) of the corrections on the
      paper's design; `tuned`: which of
      `TUNABLE` are tuned (the others stay at the (38)/(25) values).

    **Objective** (see `tuning.objectives`)

    - `w_pos`, `w_settle`, `w_noise`, `w_stab`: weights of the RMS position error after
      the transient (per `theta_unit_deg`), the settling-time surrogate (per
      `settle_unit_s`), the speed-estimate noise (per `noise_unit_rad_s`) and the
      stability/feasibility penalty.
    - `objective`: `"robust"` (smooth maximum over scenarios with `temperature`, in loss
      units) or `"average"`.
    - `hurwitz_margin` (rad/s): required decay rate of the linearised error dynamics at
      the designed equilibrium; `n_grid`: grid of the equilibrium search.
    - `diverged_loss`: the loss of a run that diverged (finite, large).

    **Optimiser**

    - `optimiser`: `"adam"` (optax), `"bfgs"` or `"lm"` (optimistix).
    - `steps`, `learning_rate` (Adam), `patience` and `min_improvement` (early stopping:
      the best loss improved by less than `min_improvement`, relative, over the last
      `patience` steps), `seed` (noise keys and random search).
    - `save_every`: samples kept per run (every n-th), bounds memory.
    """

    motor: str = "zhang750"
    observer: str = "eso"
    T_s: float = 125e-6
    t_end: float = 0.2
    t_transient: float = 0.1
    theta_err0_deg: float = 30.0
    noise_std: float = 0.02
    speeds_pu: tuple = (0.2, 0.6, 1.0)
    loads_pu: tuple = (0.0, 0.5)
    mismatch: tuple = (0.5, 1.5)
    n_mismatch: int = 3
    mismatch_values: tuple | None = None
    n_heldout: int = 4
    nodes_pu: tuple = (0.2, 0.6, 1.0)
    w2_paper_hz: float = 50.0
    bounds: Bounds = dataclasses.field(default_factory=Bounds)
    tuned: tuple = TUNABLE
    w_pos: float = 1.0
    w_settle: float = 1.0
    w_noise: float = 1.0
    w_stab: float = 10.0
    theta_unit_deg: float = 1.0
    settle_unit_s: float = 0.01
    noise_unit_rad_s: float = 0.1
    objective: str = "robust"
    temperature: float = 0.5
    hurwitz_margin: float = 20.0
    n_grid: int = 64
    diverged_loss: float = 1e3
    optimiser: str = "adam"
    steps: int = 80
    learning_rate: float = 0.1
    patience: int = 15
    min_improvement: float = 1e-3
    seed: int = 0
    save_every: int = 4

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731
        if self.motor not in pj.PRESET_NAMES:
            raise ValueError(f"Unknown motor {self.motor!r}; choose one of "
                             f"{', '.join(pj.PRESET_NAMES)}.")
        for name, allowed in (("observer", OBSERVERS), ("objective", OBJECTIVES),
                              ("optimiser", OPTIMISERS)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"`TuningConfig({name}=...)` must be one of "
                                 f"{', '.join(allowed)}; got {getattr(self, name)!r}.")
        for name, unit in (("T_s", "s"), ("t_end", "s"), ("theta_unit_deg", "deg"),
                           ("settle_unit_s", "s"), ("noise_unit_rad_s", "rad/s"),
                           ("temperature", "loss units"), ("diverged_loss", "loss units")):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ValueError(f"`TuningConfig({name}=...)` ({unit}) must be a finite "
                                 f"number > 0; got {v!r}.")
        for name in ("noise_std", "w_pos", "w_settle", "w_noise", "w_stab",
                     "hurwitz_margin", "learning_rate", "min_improvement"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"`TuningConfig({name}=...)` must be a finite number "
                                 f">= 0; got {v!r}.")
        if not 0 <= self.t_transient < self.t_end:
            raise ValueError(f"`TuningConfig(t_transient=...)` must lie in [0, t_end) = "
                             f"[0, {self.t_end}) s; got {self.t_transient!r}.")
        if not -180 < self.theta_err0_deg < 180:
            raise ValueError("`TuningConfig(theta_err0_deg=...)` must lie in (-180, 180) "
                             f"deg; got {self.theta_err0_deg!r}.")
        for name in ("n_mismatch", "n_heldout", "steps", "patience", "save_every", "n_grid",
                     "seed"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"`TuningConfig({name}=...)` must be an integer >= 0; "
                                 f"got {v!r}.")
        if self.save_every < 1 or self.n_grid < 16:
            raise ValueError("`TuningConfig(save_every=...)` must be >= 1 and "
                             "`n_grid` >= 16.")
        n = int(round(self.t_end / self.T_s))
        if n < 8 or n % self.save_every:
            raise ValueError(
                f"`TuningConfig(save_every={self.save_every})` must divide the number of "
                f"steps t_end / T_s = {n} (>= 8).")
        # speeds, loads, nodes
        for name in ("speeds_pu", "loads_pu", "nodes_pu"):
            v = _tuple(getattr(self, name))
            if not v:
                raise ValueError(f"`TuningConfig({name}=...)` is empty: give at least one "
                                 f"value.")
            if not all(math.isfinite(x) for x in v):
                raise ValueError(f"`TuningConfig({name}=...)` must be finite; got {v}.")
            set_(name, v)
        if any(s == 0 for s in self.speeds_pu):
            raise ValueError("`TuningConfig(speeds_pu=...)` must not contain 0: at standstill "
                             "the flux observer has no back-EMF to track (and (17) has "
                             "w1^2/w0).")
        if any(abs(s) > 2 for s in self.speeds_pu):
            raise ValueError(f"`TuningConfig(speeds_pu=...)` must lie within +-2 p.u.; got "
                             f"{self.speeds_pu}.")
        if any(x < 0 for x in self.nodes_pu) or any(
                b <= a for a, b in zip(self.nodes_pu, self.nodes_pu[1:])):
            raise ValueError("`TuningConfig(nodes_pu=...)` must be >= 0 and strictly "
                             f"increasing; got {self.nodes_pu}.")
        drive = pj.preset(self.motor)
        psi_f = float(drive.three_phase_motor.psi_f)
        i_q = [abs(x) * float(drive.tau_rated) / (float(drive.k_tau) * psi_f)
               for x in self.loads_pu]
        if max(i_q) >= float(drive.i_max):
            raise ValueError(f"`TuningConfig(loads_pu=...)` {self.loads_pu} needs i_q up to "
                             f"{max(i_q):.3g} A, above the drive's limit {drive.i_max:.3g} A.")
        # mismatch
        try:
            lo, hi = _tuple(self.mismatch)
        except ValueError:
            raise ValueError("`TuningConfig(mismatch=...)` must be a pair (lo, hi) of "
                             f"inductance factors; got {self.mismatch!r}.") from None
        if not (0 < lo <= hi and math.isfinite(hi)):
            raise ValueError("`TuningConfig(mismatch=...)` (L_hat / L) must satisfy "
                             f"0 < lo <= hi; got ({lo!r}, {hi!r}).")
        set_("mismatch", (lo, hi))
        if self.mismatch_values is not None:
            mv = _tuple(self.mismatch_values)
            if any(not (math.isfinite(x) and x > 0) for x in mv):
                raise ValueError("`TuningConfig(mismatch_values=...)` (L_hat / L) must be "
                                 f"finite and > 0; got {mv}.")
            set_("mismatch_values", mv)
        if not self.training_mismatch():
            raise ValueError("The mismatch grid is empty: set `n_mismatch` >= 1 (or give "
                             "`mismatch_values`).")
        if self.n_heldout < 1:
            raise ValueError("The held-out mismatch grid is empty: set `n_heldout` >= 1.")
        common = set(np.round(self.training_mismatch(), 12)) & set(
            np.round(self.heldout_mismatch(), 12))
        if common:
            raise ValueError(f"The held-out mismatch grid shares values {sorted(common)} "
                             "with the training grid; change `n_heldout` or `n_mismatch`.")
        if isinstance(self.bounds, dict):
            unknown = [k for k in self.bounds if k not in TUNABLE]
            if unknown:
                raise ValueError(f"`TuningConfig(bounds=...)`: unknown quantity "
                                 f"{', '.join(map(repr, unknown))}; choose from "
                                 f"{', '.join(TUNABLE)}.")
            set_("bounds", Bounds(**{k: tuple(v) for k, v in self.bounds.items()}))
        if not isinstance(self.bounds, Bounds):
            raise ValueError(f"`TuningConfig(bounds=...)` must be a `tuning.Bounds`; got "
                             f"{type(self.bounds).__name__}.")
        tuned = tuple(self.tuned)
        if not tuned or any(n not in TUNABLE for n in tuned) or len(set(tuned)) != len(tuned):
            raise ValueError(f"`TuningConfig(tuned=...)` must be distinct names from "
                             f"{', '.join(TUNABLE)}; got {tuned}.")
        if self.observer == "afo" and any(n in tuned for n in ("nu2", "nu3")):
            tuned = tuple(n for n in tuned if n not in ("nu2", "nu3"))
            if not tuned:
                raise ValueError("`AFOObserver` uses the PI law (53): nu2, nu3 do not apply.")
        set_("tuned", tuned)
        # the starting design must lie inside the bounds (raises a clear ValueError)
        self.initial_schedule()

    # --- derived quantities ----------------------------------------------------------

    @property
    def n_steps(self) -> int:
        return int(round(self.t_end / self.T_s))

    def drive(self) -> pj.Drive:
        return pj.preset(self.motor)

    def controller(self) -> pj.FOC:
        return pj.FOC.from_drive(self.drive())

    def training_mismatch(self) -> tuple:
        if self.mismatch_values is not None:
            return self.mismatch_values
        lo, hi = self.mismatch
        if self.n_mismatch == 1:
            return (0.5 * (lo + hi),)
        return _tuple(np.linspace(lo, hi, self.n_mismatch))

    def heldout_mismatch(self) -> tuple:
        lo, hi = self.mismatch
        if lo == hi:
            lo, hi = 0.9 * lo, 1.1 * hi
        k = np.arange(self.n_heldout) + 0.5
        return _tuple(lo + (hi - lo) * k / self.n_heldout)

    def paper_design(self) -> pj.ESODesign:
        """The paper's design: (38) flux gains, (25) speed gains at `w2_paper_hz`."""
        return pj.ESODesign.zhang38(float(self.drive().w_rated),
                                    2 * math.pi * self.w2_paper_hz, 1.0)

    def initial_schedule(self) -> GainSchedule:
        """The paper's design (38)/(25) as a `GainSchedule` (all corrections 1): the
        starting point of the tuner and the baseline every result is compared with."""
        return zhang38_schedule(float(self.drive().w_rated), self.nodes_pu,
                                w2=2 * math.pi * self.w2_paper_hz, bounds=self.bounds)

    def replace(self, **changes) -> TuningConfig:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["bounds"] = {n: list(getattr(self.bounds, n)) for n in TUNABLE}
        return d

    @classmethod
    def quick(cls, **changes) -> TuningConfig:
        """A tiny configuration (tests, smoke runs): 2 x 2 mismatch grid at one speed and
        one load, 0.1 s runs at 4 kHz, a two-node schedule, 12 Adam steps."""
        kw = dict(T_s=250e-6, t_end=0.1, t_transient=0.05, speeds_pu=(0.4,),
                  loads_pu=(0.5,), n_mismatch=2, n_heldout=3, nodes_pu=(0.2, 0.6),
                  steps=12, patience=6, learning_rate=0.15, n_grid=32, save_every=2)
        kw.update(changes)
        return cls(**kw)


class ScenarioSet(eqx.Module):
    """A flat batch of scenarios (one entry per run).

    - `k_d`, `k_q`: observer inductance factors $\\hat L_d/L_d$, $\\hat L_q/L_q$ (-).
    - `speed_pu`: rotor speed (p.u. of rated); `load_pu`: load (p.u. of rated torque).
    - `keys`: PRNG key of each run's current noise.
    """

    k_d: jnp.ndarray
    k_q: jnp.ndarray
    speed_pu: jnp.ndarray
    load_pu: jnp.ndarray
    keys: jnp.ndarray

    def __check_init__(self):
        n = np.shape(self.k_d)[0] if np.ndim(self.k_d) else 0
        if n == 0:
            raise ValueError("`ScenarioSet` is empty: the mismatch grid has no points.")

    @property
    def n(self) -> int:
        return int(np.shape(self.k_d)[0])

    def table(self) -> list[dict]:
        """One dict per scenario (plain floats), for reports."""
        return [dict(k_d=float(a), k_q=float(b), speed_pu=float(c), load_pu=float(d))
                for a, b, c, d in zip(np.asarray(self.k_d), np.asarray(self.k_q),
                                      np.asarray(self.speed_pu), np.asarray(self.load_pu))]


def make_scenarios(k_values, speeds_pu, loads_pu, *, seed: int = 0, k_q_values=None
                   ) -> ScenarioSet:
    """Product grid $k_d \\times k_q \\times$ speed $\\times$ load as a `ScenarioSet`.

    `k_values`: inductance factors for $k_d$ (and $k_q$ unless `k_q_values` is given).
    The noise key of scenario `j` is `fold_in(PRNGKey(seed), j)`.
    """
    kd = np.asarray(k_values, dtype=float).reshape(-1)
    kq = kd if k_q_values is None else np.asarray(k_q_values, dtype=float).reshape(-1)
    sp = np.asarray(speeds_pu, dtype=float).reshape(-1)
    ld = np.asarray(loads_pu, dtype=float).reshape(-1)
    for name, v in (("k_values", kd), ("k_q_values", kq), ("speeds_pu", sp),
                    ("loads_pu", ld)):
        if v.size == 0:
            raise ValueError(f"`make_scenarios({name}=...)` is empty: the scenario grid "
                             "would have no points.")
    if np.any(~np.isfinite(kd)) or np.any(kd <= 0) or np.any(~np.isfinite(kq)) \
            or np.any(kq <= 0):
        raise ValueError("inductance factors L_hat / L must be finite and > 0.")
    grid = np.stack(np.meshgrid(kd, kq, sp, ld, indexing="ij"), -1).reshape(-1, 4)
    base = jr.PRNGKey(seed)
    keys = jax.vmap(lambda j: jr.fold_in(base, j))(jnp.arange(grid.shape[0]))
    return ScenarioSet(k_d=jnp.asarray(grid[:, 0]), k_q=jnp.asarray(grid[:, 1]),
                       speed_pu=jnp.asarray(grid[:, 2]), load_pu=jnp.asarray(grid[:, 3]),
                       keys=keys)


def training_scenarios(config: TuningConfig) -> ScenarioSet:
    """The training grid of `config` (noise keys from `seed`)."""
    return make_scenarios(config.training_mismatch(), config.speeds_pu, config.loads_pu,
                          seed=config.seed)


def heldout_scenarios(config: TuningConfig) -> ScenarioSet:
    """The held-out grid: mismatch values disjoint from training, other noise keys."""
    return make_scenarios(config.heldout_mismatch(), config.speeds_pu, config.loads_pu,
                          seed=config.seed + 10_000)


def observer_motor(drive: pj.Drive, k_d, k_q) -> pj.PMSMParams:
    """The observer's machine model: the drive's with $L_d$, $L_q$ scaled by `k_d`, `k_q`."""
    m = drive.three_phase_motor
    return eqx.tree_at(lambda p: (p.L_d, p.L_q), m, (m.L_d * k_d, m.L_q * k_q))


def make_observer(kind: str, motor: pj.PMSMParams, design) -> pj.AbstractObserver:
    """`"eso"` -> `ESOObserver(motor, design)` (fal `a = 0.5`, `eta = 0.05 psi_f`),
    `"leso"` -> `LESOObserver`, `"afo"` -> `AFOObserver`."""
    if kind == "eso":
        return pj.ESOObserver(motor, design)
    if kind == "leso":
        return pj.LESOObserver(motor, design)
    if kind == "afo":
        return pj.AFOObserver(motor, design)
    raise ValueError(f"unknown observer {kind!r}; choose one of {', '.join(OBSERVERS)}.")


def operating_current(drive: pj.Drive, load_pu):
    """Controlled current $(i_d, i_q) = (0, \\tau_L / (k_\\tau\\psi_f))$ (A) for a load in
    p.u. of rated torque ($i_d = 0$: the torque is $k_\\tau\\psi_f i_q$)."""
    i_q = load_pu * drive.tau_rated / (drive.k_tau * drive.three_phase_motor.psi_f)
    return jnp.stack([jnp.zeros_like(i_q), i_q], -1)


def simulate_scenarios(design, config: TuningConfig, scenarios: ScenarioSet, *,
                       save_every: int | None = None, kind: str | None = None
                       ) -> pj.Trajectory:
    """Run every scenario with observer gains `design` (vmapped, `throw=False`).

    `design` is any gain schedule (`GainSchedule`, `ESODesign`, `FixedGains`); `kind`
    overrides `config.observer`. Returns a batched `Trajectory` (leading axis: scenario).
    """
    drive = config.drive()
    foc = config.controller()
    kind = config.observer if kind is None else kind
    save_every = config.save_every if save_every is None else save_every
    sensing = pj.Sensing(noise_std=float(config.noise_std))
    w_r = float(drive.w_rated)
    theta_hat0 = -math.radians(config.theta_err0_deg)

    def one(k_d, k_q, speed_pu, load_pu, key):
        obs = make_observer(kind, observer_motor(drive, k_d, k_q), design)
        w = speed_pu * w_r
        i0 = operating_current(drive, load_pu)
        sc = pj.Scenario(t_end=config.t_end, w_m_imposed=pj.Profile.constant(w),
                         i_d_ref=pj.Profile.constant(i0[0]),
                         i_q_ref=pj.Profile.constant(i0[1]))
        return pj.simulate(drive, foc, obs, sc, T_s=config.T_s, sensing=sensing,
                           key=key if config.noise_std > 0 else None, theta0=0.0,
                           w_m0=w, theta_hat0=theta_hat0, i_dq0=(i0[0], i0[1]),
                           save_every=save_every, throw=False)

    return jax.vmap(one)(scenarios.k_d, scenarios.k_q, scenarios.speed_pu,
                         scenarios.load_pu, scenarios.keys)
