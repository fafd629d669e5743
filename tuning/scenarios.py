r"""Scenario sets as data: closed-loop sensorless runs as the drive will run them.

Every run, in training, held-out and validation alike, is a closed loop in which nothing
is imposed: the speed controller acts on the observer's speed estimate, the current
control runs in the observer's angle, the rotor's mechanical equation is integrated
(`pmsmjax.simulate` with `Scenario(w_m_ref=...)`). A run is one row of a `ScenarioSet`:

- the rotor starts turning at `s0` (p.u. of rated speed, signed), the observer on the true
  angle and speed;
- the speed reference ramps from `s0` to `s1` over `[t0, t1]` (s): an acceleration, a
  deceleration, or a **reversal through zero** (`s1` of the other sign);
- a braking **load step** to `load_pu` (p.u. of rated torque, against the final
  direction) at `t_load`;
- the observer's machine model has $\hat L_d = k_d L_d$, $\hat L_q = k_q L_q$,
  $\hat R_s = k_R R_s$, $\hat\psi_f = k_\psi \psi_f$ (the plant and the controller keep
  the true values);
- the sampled currents carry white noise `k_noise x noise_std` drawn from the run's key.

**Training and held-out runs** (`training_set`, `heldout_set`) come in three kinds, in
turn: *ramp* (between two speeds of one sign), *reversal* and *load* (constant speed, a
load step up to `load_max_pu`). The ramps' acceleration is a fraction (`accel_range`) of
$a_{max} = n_p \tau_{max} / J$, what the speed controller's torque limit gives the
unloaded rotor: the fast ones reach the current limit.
Their model errors come in patterns (`TuningProblem.train_errors`, default
"structured"): consecutive triples of runs, one of each kind, take `ERROR_PATTERNS` in
turn: every parameter at once, both inductances, then each of $L_d$, $L_q$, $R_s$,
$\psi_f$ and the noise alone, the rest matched. The validation cases hold one error at
a time and the inductances jointly; a search that saw only runs with every parameter
wrong at once traded those away (measured 12-03 with `train_errors="joint"`: the
rotor-flux observer's design stayed the paper's, the ESO's worst validation run was 7.5 %
worse).

**Validation runs** (`validation_set`): every case of `val_cases` at every speed of
`val_speeds_pu` with both signs; a ramp from `val_start_frac` of the final speed over
$[0.1, 0.3]\,t_{end}$ and a load step to `val_load_pu` at $0.6\,t_{end}$.

**Disjoint by construction**: speeds, mismatch values and noise keys of the three sets
never coincide (a matched parameter, 1.0, is no error and is not compared). Training
values lie on a grid of step 0.05 offset by 1/4 step, held-out values on the same grid
offset by 3/4 step (speeds and ratios), and a value within 1/8 step of a validation
value is moved away by a quarter step; the noise keys are
`fold_in(PRNGKey(seed), set)` with a different `set` each. `check_disjoint` verifies it
and the report states it.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

import pmsmjax as pj
from pmsmjax.analysis import equilibria_traced
from pmsmjax.observers import OperatingPoint

from .problem import TuningProblem


KINDS = ("ramp", "reversal", "load")
#: Grid of the drawn speeds and ratios, and the offsets of the training / held-out values.
GRID = 0.05
OFFSETS = {"train": 0.25, "heldout": 0.75}
#: Noise-key streams of the three sets.
STREAMS = {"train": 1, "heldout": 2, "validation": 3}
#: Validation: ramp over this fraction of the run, load step at this fraction.
VAL_RAMP = (0.1, 0.3)
VAL_LOAD_STEP = 0.6
#: The model errors of the training and held-out runs under `train_errors="structured"`,
#: in turn, three runs (one of each kind) per pattern: the factors each pattern draws,
#: the others matched (1.0).
ERROR_PATTERNS = (("k_d", "k_q", "k_R", "k_psi", "k_noise"), ("k_d", "k_q"), ("k_d",),
                  ("k_q",), ("k_R",), ("k_psi",), ("k_noise",))
#: The search's sets under the low-speed rule (`search_set`): at most this many larger
#: draws, and at most this many times the runs asked for.
SEARCH_REDRAWS = 4
SEARCH_DRAW_MAX = 4
#: The phases of a run, by its scenario's times: `start` `[0, t0)` (before the speed
#: ramp), `ramp` `[t0, t1)`, `steady` `[t1, t_load)` (between the ramp and the load
#: step), `loaded` `[t_load, t_end]` (the load step and after).
PHASES = ("start", "ramp", "steady", "loaded")


def phase_at(t_s, t0, t1, t_load) -> str:
    """The phase (`PHASES`) of a run with ramp `[t0, t1)` and load step at `t_load`
    (s) under way at time `t_s` (s); "unknown" where `t_s` is not finite."""
    if not np.isfinite(t_s):
        return "unknown"
    return PHASES[int(np.searchsorted([t0, t1, t_load], t_s, side="right"))]


def phase_counts(phases) -> str:
    """`"ramp 1, loaded 2"`: how many of `phases` (names from `phase_at`) fall in each
    phase, in the order of `PHASES`, phases without any left out."""
    phases = list(phases)
    return ", ".join(f"{p} {phases.count(p)}" for p in (*PHASES, "unknown")
                     if phases.count(p))
_CASE = ("k_d", "k_q", "k_R", "k_psi", "k_noise")


class ScenarioSet(eqx.Module):
    """A flat batch of closed-loop runs (one entry per run; see the module docstring).

    `s0`, `s1` (p.u., signed), `t0`, `t1`, `t_load` (s), `load_pu` (p.u., >= 0),
    `k_d`, `k_q`, `k_R`, `k_psi`, `k_noise` (-), `keys`, `kind` (0 ramp, 1 reversal,
    2 load; 3 validation), and `t_end` (s, static: one length per set).
    """

    s0: jnp.ndarray
    s1: jnp.ndarray
    t0: jnp.ndarray
    t1: jnp.ndarray
    t_load: jnp.ndarray
    load_pu: jnp.ndarray
    k_d: jnp.ndarray
    k_q: jnp.ndarray
    k_R: jnp.ndarray
    k_psi: jnp.ndarray
    k_noise: jnp.ndarray
    keys: jnp.ndarray
    kind: jnp.ndarray
    t_end: float = eqx.field(static=True)

    @property
    def n(self) -> int:
        return int(np.shape(self.s0)[0])

    def table(self) -> list[dict]:
        """One dict per run (plain numbers), for reports."""
        names = ("s0", "s1", "t0", "t1", "t_load", "load_pu", *_CASE)
        cols = {k: np.asarray(getattr(self, k), dtype=float) for k in names}
        kind = np.asarray(self.kind)
        return [{"kind": (*KINDS, "validation")[int(kind[j])],
                 **{k: round(float(v[j]), 6) for k, v in cols.items()}}
                for j in range(self.n)]

    def take(self, idx) -> ScenarioSet:
        """The runs `idx` (indices)."""
        idx = np.asarray(idx)
        return jax.tree_util.tree_map(lambda x: x[idx], self)


def max_acceleration(drive: pj.Drive, foc: pj.FOC) -> float:
    """$a_{max} = n_p \\tau_{max} / J$ (electrical rad/s^2): the speed controller's torque
    limit on the unloaded rotor."""
    return float(drive.three_phase_motor.n_p * foc.speed.tau_max / drive.mechanics.J)


def _values(rng, lo, hi, n, offset, avoid):
    """`n` values on the grid `GRID` over [lo, hi] offset by `offset` steps, drawn with
    replacement, and moved a quarter step away from any value of `avoid` within 1/8
    step."""
    start = math.floor(lo / GRID)
    grid = (np.arange(start, math.ceil(hi / GRID) + 1) + offset) * GRID
    grid = grid[(grid >= lo - 1e-12) & (grid <= hi + 1e-12)]
    if grid.size == 0:
        grid = np.array([0.5 * (lo + hi)])
    x = rng.choice(grid, size=n)
    for a in avoid:
        close = np.abs(x - a) < GRID / 8
        x = np.where(close, x + GRID / 4, x)
    return x


def _draw(problem: TuningProblem, split: str, n: int) -> ScenarioSet:
    drive, foc = problem.drive(), problem.controller()
    rng = np.random.default_rng([problem.seed, STREAMS[split]])
    off = OFFSETS[split]
    val_speeds = [abs(s) for s in problem.val_speeds_pu] + \
        [problem.val_start_frac * abs(s) for s in problem.val_speeds_pu]
    val = np.asarray(problem.val_cases, dtype=float)
    kind = np.arange(n) % len(KINDS)
    sp = _values(rng, *problem.speed_range, 2 * n, off, val_speeds).reshape(2, n)
    sign = rng.choice([-1.0, 1.0], size=n)
    s0 = sign * sp[0]
    s1 = np.where(kind == 1, -sign * sp[1], np.where(kind == 2, s0, sign * sp[1]))
    a = rng.uniform(*problem.accel_range, size=n) * max_acceleration(drive, foc)
    w_r = float(drive.w_rated)
    t_end = float(problem.t_end)
    t0 = np.full(n, 0.1 * t_end)
    # the ramp takes |s1 - s0| w_r / a, at most half the run (then faster, but never
    # faster than a_max: the reference stays within what the torque limit can follow)
    dw = np.abs(s1 - s0) * w_r
    dur = np.maximum(np.minimum(dw / a, 0.5 * t_end), dw / max_acceleration(drive, foc))
    t1 = t0 + np.maximum(dur, 2 * problem.T_s)
    load = np.where(kind == 2, rng.uniform(0.5, 1.0, size=n),
                    rng.uniform(0.0, 0.5, size=n)) * problem.load_max_pu
    t_load = np.where(kind == 2, 0.3 * t_end, 0.75 * t_end)
    k = {name: _values(rng, *rng_, n, off, val[:, j])
         for j, (name, rng_) in enumerate((("k_d", problem.mismatch_range),
                                           ("k_q", problem.mismatch_range),
                                           ("k_R", problem.resistance_range),
                                           ("k_psi", problem.flux_range)))}
    k["k_noise"] = rng.uniform(*problem.noise_range, size=n)
    if problem.train_errors == "structured":
        pattern = (np.arange(n) // len(KINDS)) % len(ERROR_PATTERNS)
        for name in k:
            active = np.array([name in ERROR_PATTERNS[p] for p in pattern])
            k[name] = np.where(active, k[name], 1.0)
    keys = jr.split(jr.fold_in(jr.PRNGKey(problem.seed), STREAMS[split]), n)
    f = lambda x: jnp.asarray(x, dtype=float)  # noqa: E731
    return ScenarioSet(s0=f(s0), s1=f(s1), t0=f(t0), t1=f(t1), t_load=f(t_load),
                       load_pu=f(load), **{n_: f(v) for n_, v in k.items()}, keys=keys,
                       kind=jnp.asarray(kind), t_end=t_end)


def training_set(problem: TuningProblem) -> ScenarioSet:
    """The `problem.n_train` training runs (see the module docstring)."""
    return _draw(problem, "train", problem.n_train)


def heldout_set(problem: TuningProblem) -> ScenarioSet:
    """The `problem.n_heldout` held-out runs: the training runs' kinds and ranges, other
    values and keys (used to choose among the searches' designs, never to search)."""
    return _draw(problem, "heldout", problem.n_heldout)


def validation_set(problem: TuningProblem) -> ScenarioSet:
    """Every case of `problem.val_cases` at every speed of `problem.val_speeds_pu`, both
    signs (see the module docstring)."""
    speeds = [s for v in problem.val_speeds_pu for s in (v, -v)]
    rows = np.array([(s, *c) for c in problem.val_cases for s in speeds], dtype=float)
    n = rows.shape[0]
    t_end = float(problem.val_t_end)
    q = lambda x: round(x * t_end / problem.T_s) * problem.T_s  # noqa: E731
    f = lambda x: jnp.asarray(x, dtype=float)  # noqa: E731
    keys = jr.split(jr.fold_in(jr.PRNGKey(problem.seed), STREAMS["validation"]), n)
    return ScenarioSet(
        s0=f(problem.val_start_frac * rows[:, 0]), s1=f(rows[:, 0]),
        t0=f(np.full(n, q(VAL_RAMP[0]))), t1=f(np.full(n, q(VAL_RAMP[1]))),
        t_load=f(np.full(n, q(VAL_LOAD_STEP))), load_pu=f(np.full(n, problem.val_load_pu)),
        **{name: f(rows[:, 1 + j]) for j, name in enumerate(_CASE)}, keys=keys,
        kind=jnp.full(n, 3), t_end=t_end)


def check_disjoint(*sets: ScenarioSet) -> dict:
    """Verify that no speed, mismatch ratio or noise key of one set occurs in another;
    `ValueError` naming the first overlap. Returns, per quantity, the smallest distance
    between two sets' values (for the report)."""
    out = {}
    for q in ("speed", "k_d", "k_q", "k_R", "k_psi", "key"):
        vals = []
        for s in sets:
            if q == "speed":
                v = np.abs(np.concatenate([np.asarray(s.s0), np.asarray(s.s1)]))
            elif q == "key":
                v = np.asarray(jax.random.key_data(s.keys) if jnp.issubdtype(
                    s.keys.dtype, jax.dtypes.prng_key) else s.keys).reshape(s.n, -1)
                v = np.array([hash(r.tobytes()) for r in v], dtype=float)
            else:
                v = np.asarray(getattr(s, q))
                v = v[np.abs(v - 1.0) > 1e-12] if not _all_one(v) else v
            vals.append(np.unique(v))
        dmin = math.inf
        for i in range(len(vals)):
            for j in range(i + 1, len(vals)):
                d = np.min(np.abs(vals[i][:, None] - vals[j][None, :]))
                if q == "key" and d == 0:
                    raise ValueError(f"scenario sets {i} and {j} share a noise key")
                if q not in ("key", "k_d", "k_q", "k_R", "k_psi") and d < 1e-9:
                    raise ValueError(f"scenario sets {i} and {j} share a speed {q}")
                if q in ("k_d", "k_q", "k_R", "k_psi") and d < 1e-9 and not (
                        _all_one(vals[i]) or _all_one(vals[j])):
                    raise ValueError(f"scenario sets {i} and {j} share a value of {q}")
                dmin = min(dmin, float(d))
        out[q] = dmin if q != "key" else "distinct"
    return out


def _all_one(v) -> bool:
    return bool(np.all(np.abs(v - 1.0) < 1e-12))


def observer_model(drive: pj.Drive, k_d, k_q, k_R, k_psi) -> pj.PMSMParams:
    """The observer's machine model: the drive's with $L_d$, $L_q$, $R_s$, $\\psi_f$
    scaled by the factors (observer value / plant value)."""
    return pj.scale_motor(drive.three_phase_motor,
                       {"L_d": k_d, "L_q": k_q, "R_s": k_R, "psi_f": k_psi})


def scenario(drive: pj.Drive, s0, s1, t0, t1, t_load, load_pu, t_end) -> pj.Scenario:
    """The `pmsmjax.Scenario` of one run (speed controlled: nothing imposed)."""
    w_r = float(drive.w_rated)
    tau = load_pu * float(drive.tau_rated) * jnp.sign(s1)
    return pj.Scenario(t_end=t_end,
                       w_m_ref=pj.Profile(jnp.stack([t0, t1]), jnp.stack([s0 * w_r,
                                                                          s1 * w_r])),
                       tau_L=pj.Profile(jnp.stack([t_load, t_load]),
                                        jnp.stack([0.0 * tau, tau])))


def simulate_set(make_observer, drive: pj.Drive, foc: pj.FOC, sset: ScenarioSet, *,
                 T_s: float, noise_std: float, save_every: int,
                 speed_from_angle: float | None = None) -> pj.Trajectory:
    """Run every scenario of `sset` (vmapped, `throw=False`): `make_observer(motor)`
    builds the observer (its design already applied; traced values allowed) with the
    observer-model `motor`; `speed_from_angle` (Hz): the controller takes the speed of
    its angle (`pmsmjax.SpeedFromAngle`) instead of its own speed estimate."""
    w_r = float(drive.w_rated)
    noisy = noise_std > 0

    def one(s0, s1, t0, t1, t_load, load_pu, k_d, k_q, k_R, k_psi, k_noise, key):
        obs = make_observer(observer_model(drive, k_d, k_q, k_R, k_psi))
        if speed_from_angle is not None:
            obs = pj.SpeedFromAngle(obs, w_track=2 * math.pi * speed_from_angle)
        sc = scenario(drive, s0, s1, t0, t1, t_load, load_pu, sset.t_end)
        return pj.simulate(drive, foc, obs, sc, T_s=T_s,
                           sensing=pj.Sensing(noise_std=noise_std * k_noise),
                           key=key if noisy else None, theta0=0.0, w_m0=s0 * w_r,
                           theta_hat0=0.0, save_every=save_every, throw=False)

    return jax.vmap(one)(sset.s0, sset.s1, sset.t0, sset.t1, sset.t_load, sset.load_pu,
                         sset.k_d, sset.k_q, sset.k_R, sset.k_psi, sset.k_noise, sset.keys)


def operating_current(drive: pj.Drive, load_pu):
    """Controlled current $(i_d, i_q) = (0, \\tau_L / (k_\\tau\\psi_f))$ (A) for a load
    in p.u. of rated torque ($i_d = 0$)."""
    i_q = load_pu * drive.tau_rated / (drive.k_tau * drive.three_phase_motor.psi_f)
    return jnp.stack([jnp.zeros_like(i_q), i_q], -1)


def designed_feasible(observer, drive: pj.Drive, speed_pu, load_pu) -> dict:
    """The equilibrium analysis of `observer` (its design and machine model applied) on
    `drive`'s machine at constant speed `speed_pu` (p.u. of rated, signed) and the
    controlled current of the braking load `load_pu` (p.u. of rated torque,
    `operating_current`). The load opposes the rotation, as in the runs (`scenario`),
    so the current takes the speed's sign: motoring in both directions. `feasible`
    where its designed equilibrium (the principal one, nearest zero angle error) is
    stable and no other one is, else False; `status` the analysis's (0 ok, 2 no
    equilibrium at all, -1 failed: no verdict). The family's own route where it has
    one, else the generic route (`pmsmjax.analysis.equilibria_traced`). Traceable and
    vmappable."""
    op = OperatingPoint(speed_pu * float(drive.w_rated),
                        operating_current(drive, load_pu * jnp.sign(speed_pu)))
    plant = drive.three_phase_motor
    eq = observer.fast_equilibria(plant, op)
    if eq is None:
        tol = float(jnp.finfo(op.w_m.dtype).eps) ** 0.6
        eq = equilibria_traced(observer, plant, op, method="generic", n_grid=64,
                               max_roots=8, tol=tol)
    valid = eq.valid & (eq.status == 0)
    principal = jnp.arange(valid.shape[-1]) == eq.principal
    p_stable = jnp.any(principal & valid & eq.stable)
    other_stable = jnp.any(~principal & valid & eq.stable)
    feasible = (eq.status == 0) & p_stable & ~other_stable
    return dict(feasible=feasible, status=jnp.asarray(eq.status, jnp.int32))


def sensored_lowest_speed(problem, sset: ScenarioSet, runs) -> list[dict]:
    """The runs `runs` (indices into `sset`) of `problem`'s drive and controller with the
    sensored observer (the true angle and speed; the same noise), a reference no observer
    can better: per run the lowest speed magnitude the rotor reaches in the run
    (`lowest_speed_pu`, p.u. of rated), when (`t_s`, s), the back-EMF amplitude there
    (`back_emf_V`, |w| psi_f, V), the current amplitude there (`current_A`, A), and
    whether the rotor reverses (`reverses`). Where that speed is low, the back-EMF an
    observer reads is small against its model errors."""
    runs = [int(j) for j in runs]
    if not runs:
        return []
    drive = problem.drive()
    idx = np.asarray(runs)
    sub = jax.tree_util.tree_map(lambda a: a[idx], sset)
    traj = simulate_set(lambda motor: pj.SensoredObserver(), drive, problem.controller(),
                        sub, T_s=problem.T_s, noise_std=problem.noise_std, save_every=1)
    w, t, i = np.asarray(traj.w_m), np.asarray(traj.t), np.asarray(traj.i_dq)
    s1 = np.asarray(sub.s1)
    w_r, psi_f = float(drive.w_rated), float(drive.motor.psi_f)
    out = []
    for j, run in enumerate(runs):
        k = int(np.argmin(np.abs(w[j])))
        out.append(dict(run=run, lowest_speed_pu=float(abs(w[j, k]) / w_r),
                        t_s=float(t[j, k]), back_emf_V=float(abs(w[j, k]) * psi_f),
                        current_A=float(np.linalg.norm(i[j, k])),
                        reverses=bool(np.any(np.sign(w[j]) == -np.sign(s1[j])))))
    return out


def low_speed_runs(problem, sset: ScenarioSet) -> tuple[np.ndarray, np.ndarray]:
    """The low-speed rule's first test (`TuningProblem.low_speed_limit_pu`, fixed before
    tuning): per run of `sset`, whether the sensored drive (`sensored_lowest_speed`: the
    same controller on the true angle and speed, the same noise) turns slower than the
    limit at some sample, and that lowest speed (p.u. of rated; NaN where the limit is 0
    and nothing is simulated). Returns `(beyond, lowest_pu)`. `apply_low_speed_rule`
    gives such a run its unloaded twin where that one stays above the limit."""
    beyond, lowest, _ = _sensored_rule(problem, sset)
    return beyond, lowest


def apply_low_speed_rule(problem, sset: ScenarioSet) -> tuple[ScenarioSet, dict]:
    """The low-speed rule (`TuningProblem.low_speed_limit_pu`, fixed before tuning), as
    every set meets it: a run in which the sensored drive turns slower than the limit
    (`low_speed_runs`) is replaced by its **unloaded twin**, the same run without its load
    step, where that twin stays above the limit in the sensored drive; a slow run's load
    step stalls even the sensored drive (at 0.1 p.u. under 0.4 p.u. load it falls to about
    1 % of rated speed), so the loaded run says nothing of the observer while the twin
    judges it at the run's own speed. A run whose twin is still beyond (a reversal, a start
    below the limit) is beyond the observer's class.

    Returns `(rule_set, rule)`: `rule_set` is `sset` with the twins in place (same runs,
    same order, `load_pu` 0 where a twin replaced a run), and `rule` holds `beyond` (per
    run: still beyond the class), `unloaded` (per run: replaced by its twin), `lowest_pu`
    (the lowest speed in the sensored drive of the run as it stands in `rule_set`, p.u.;
    NaN where the limit is 0) and `sensored` (`sensored_lowest_speed`'s record of every run
    of `rule_set`; None where the limit is 0)."""
    beyond, lowest, found = _sensored_rule(problem, sset)
    unloaded = np.zeros(sset.n, bool)
    if beyond.any():
        idx = np.nonzero(beyond)[0]
        twins = eqx.tree_at(lambda s: s.load_pu, sset.take(idx),
                            jnp.zeros(idx.size, dtype=jnp.asarray(sset.load_pu).dtype))
        still, low_t, found_t = _sensored_rule(problem, twins)
        ok = idx[~still]
        unloaded[ok] = True
        beyond[ok] = False
        lowest[ok] = low_t[~still]
        for j, r in zip(idx, found_t):
            if not beyond[j]:
                found[j] = dict(r, run=int(j))
        load = np.where(unloaded, 0.0, np.asarray(sset.load_pu))
        sset = eqx.tree_at(lambda s: s.load_pu, sset,
                           jnp.asarray(load, dtype=jnp.asarray(sset.load_pu).dtype))
    return sset, dict(beyond=beyond, unloaded=unloaded, lowest_pu=lowest, sensored=found)


def judged_speeds(sset: ScenarioSet, beyond) -> tuple[float, float] | None:
    """The final speeds (p.u., magnitudes) of the runs of `sset` the low-speed rule
    judges, `(lowest, highest)`: the speeds a verdict over them covers. None where the
    rule sets no run apart (the verdict covers every run) or every run."""
    beyond = np.asarray(beyond, bool)
    if not beyond.any() or beyond.all():
        return None
    s = np.abs(np.asarray(sset.s1, float))[~beyond]
    return float(s.min()), float(s.max())


def _sensored_rule(problem, sset: ScenarioSet):
    """`low_speed_runs` and the sensored records it measured (`sensored_lowest_speed` of
    every run; None where the limit is 0)."""
    limit = float(problem.low_speed_limit_pu)
    if limit <= 0:
        return np.zeros(sset.n, bool), np.full(sset.n, np.nan), None
    found = sensored_lowest_speed(problem, sset, range(sset.n))
    lowest = np.array([r["lowest_speed_pu"] for r in found])
    return lowest < limit, lowest, found


def search_set(problem, split: str) -> tuple[ScenarioSet, dict]:
    """The search's `split` set ("train" or "heldout") under the low-speed rule: its
    `n_train` / `n_heldout` runs, all within the rule (`apply_low_speed_rule`: unloaded
    twins in place, runs beyond the limit even unloaded left out). Where the rule leaves runs out,
    the draw is made larger (the same stream, `SEARCH_REDRAWS` times at most) and its
    first runs within the rule are kept, so the rule does not shrink what the search
    sees (li's observers leave out every reversal: a third of the runs; in runs beyond
    the limit the observer loses lock chaotically, and a design's loss there is noise).
    `ValueError` where the rule leaves no run. Returns the set
    and `{"left_out": n, "unloaded": n, "drawn": n}`: the runs of the draw up to the
    last one kept that were left out, the kept runs judged without their load step, and
    how many runs that draw took. A class without a limit gets `training_set` /
    `heldout_set` unchanged."""
    n = {"train": problem.n_train, "heldout": problem.n_heldout}[split]
    m = n
    for _ in range(SEARCH_REDRAWS):
        rule_set, rule = apply_low_speed_rule(problem, _draw(problem, split, m))
        kept = np.nonzero(~rule["beyond"])[0]
        if kept.size >= n or m >= SEARCH_DRAW_MAX * n:
            break
        m = min(SEARCH_DRAW_MAX * n, len(KINDS) * math.ceil(
            1.25 * m * n / max(kept.size, 1) / len(KINDS)))
    if not kept.size:
        raise ValueError(
            f"`TuningProblem.low_speed_limit_pu` = {problem.low_speed_limit_pu:g}: every "
            f"{split} run turns slower than it in a sensored drive, even without its load "
            f"step; lower the limit or raise the {split} speeds")
    idx = kept[:n]
    last = int(idx[-1]) + 1
    counts = {"left_out": int(rule["beyond"][:last].sum()),
              "unloaded": int(rule["unloaded"][idx].sum()), "drawn": last}
    return rule_set.take(idx), counts


__all__ = ["KINDS", "PHASES", "ScenarioSet", "apply_low_speed_rule", "check_disjoint",
           "designed_feasible", "heldout_set", "judged_speeds",
           "low_speed_runs", "max_acceleration", "search_set",
           "observer_model", "operating_current", "phase_at", "phase_counts", "scenario",
           "sensored_lowest_speed", "simulate_set", "training_set", "validation_set"]
