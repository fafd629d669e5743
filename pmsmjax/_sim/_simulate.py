"""Closed-loop simulation (the open-loop plant runs are in `_plant_run.py`).

`simulate` runs sensor -> observer -> controller -> inverter -> plant at sampling period
`T_s` with a `lax.scan` over sampling instants. The inverter voltage is held constant
(ZOH) in the stationary frame over each period and the plant is integrated inside it with
a fixed-step diffrax solver. Everything is a pure function of its inputs, so `jax.vmap`
batches runs over any PyTree leaf (parameters, gains, scenarios) and `jax.grad`
differentiates through a whole run.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jax.ad_checkpoint import checkpoint_name

from .._control._foc import FOC
from .._frames import wrap_angle
from .._plant._inverter import observer_voltage
from .._plant._motor import PMSM, PlantInput, PlantState, _is_zero, cos_sin, join_state, split_state
from .._plant._params import Drive, PMSMParams, scale_motor
from .._plant._recheck import recheck
from .._validate import NonFiniteInputError, check_positive, is_concrete
from ..observers import AbstractObserver, Measurement
from ._batching import batched_like, values_as_arrays, without_labels
from ._dtypes import cast_floats, run_dtype
from ._integrate import RK4, check_drive_step, integrate
from ._scenario import Scenario
from ._solution import RESULTS, Trajectory


_OK_NAME = "pmsmjax.simulate.ok"
_NOISE_BLOCK = 256  # current-noise samples drawn at once (see `_simulate`)
_CHECKPOINT_POLICY = jax.checkpoint_policies.save_only_these_names(_OK_NAME)


class Sensing(eqx.Module):
    """Measurement chain of the drive.

    **Arguments:**

    - `noise_std`: standard deviation of white Gaussian noise added to each sampled
      phase-current component (A). Needs `key` in `simulate` when > 0.
    - `quantum`: current quantisation step (A, one LSB); 0 = none. (Quantisation is
      piecewise constant: its derivative is zero.)
    - `delay`: current-sampling delay in whole samples (static int >= 0).
    - `encoder_quantum`: encoder angle resolution (rad); 0 = ideal encoder.
    """

    noise_std: float = 0.0
    quantum: float = 0.0
    delay: int = eqx.field(static=True, default=0)
    encoder_quantum: float = 0.0

    def __check_init__(self):
        check_positive("Sensing", "noise_std", self.noise_std, "A", allow_zero=True)
        check_positive("Sensing", "quantum", self.quantum, "A", allow_zero=True)
        check_positive("Sensing", "encoder_quantum", self.encoder_quantum, "rad",
                       allow_zero=True)
        if not isinstance(self.delay, int) or self.delay < 0:
            raise ValueError(
                f"`Sensing(delay=...)` must be an integer number of samples >= 0; got "
                f"{self.delay!r}."
            )

    def quantise(self, x, q):
        if isinstance(q, (int, float)) and q == 0:
            return x
        return jnp.where(q > 0, jnp.round(x / jnp.where(q > 0, q, 1.0)) * q, x)


def _finite_bounded(y: PlantState, i_bound, w_bound):
    """For `y` in component form: all finite, |i| < i_bound and |w_m| < w_bound."""
    i_d, i_q = y.i_dq
    ok = (i_d * i_d + i_q * i_q < i_bound ** 2) & (jnp.abs(y.w_m) < w_bound)
    for x in jax.tree_util.tree_leaves(y):
        ok = ok & jnp.isfinite(x)
    return ok


def _estimate_bounded(est, w_bound):
    """The observer's estimate is finite and its speed within `w_bound` (the plant's)."""
    return jnp.isfinite(est.theta_hat) & (jnp.abs(est.w_hat) < w_bound)


def _rotate(c, s, x, y):
    """Components of the vector (x, y) rotated by the angle with cosine c and sine s."""
    return c * x - s * y, s * x + c * y


def simulate(
    drive: Drive,
    controller: FOC,
    observer: AbstractObserver,
    scenario: Scenario,
    *,
    T_s: float = 125e-6,
    solver=RK4(),
    n_substeps: int = 1,
    sensing: Sensing = Sensing(),
    key=None,
    theta0=0.0,
    w_m0=0.0,
    theta_hat0=None,
    w_hat0=None,
    i_dq0=(0.0, 0.0),
    save_every: int = 1,
    throw: bool = True,
    observer_u_dt=None,
) -> Trajectory:
    """Simulate one closed-loop run of a (sensored or sensorless) drive.

    **Arguments:**

    - `drive`: the plant's `Drive` (machine, mechanics, inverter, ratings).
    - `controller`: `FOC` (its machine model may differ from the plant).
    - `observer`: any `AbstractObserver`; `SensoredObserver()` for sensored control.
    - `scenario`: `Scenario` with the references and disturbances.
    - `T_s`: sampling period (s).
    - `solver`: fixed-step diffrax Runge-Kutta solver for the plant (default `RK4()`).
    - `n_substeps`: solver steps per sampling period.
    - `sensing`: `Sensing` (current noise, quantisation, sampling delay, encoder).
    - `key`: `jax.random` key for the current noise (needed if `noise_std > 0`).
    - `theta0`, `w_m0`: initial rotor angle (rad) and electrical speed (rad/s).
    - `theta_hat0`, `w_hat0`: initial observer angle/speed (default: the true values);
      the initial angle error is `theta0 - theta_hat0`.
    - `i_dq0`: initial current in rotor coordinates (A).
    - `save_every`: keep every n-th sample in the trajectory (must divide the number of
      steps); the integrals `ise_*` always use every sample.
    - `throw`: raise if the run diverged (a state non-finite, a current above 20 times
      `drive.i_max`, the rotor's speed or the observer's speed estimate above 20 times
      `drive.w_rated`); with `False` the status is returned instead
      (use this under `vmap` for sweeps).
    - `observer_u_dt`: the inverter error (V) that the drive's dead-time compensation
      assumes when it hands the observer its voltage: the observer sees the commanded
      voltage of the last period less `observer_u_dt * tanh(i / i_dt)` per phase (`sign(i)`
      for the hard model, `i_dt = 0`),
      averaged over the measured currents at both ends of the period (what `replay(...,
      inverter=...)` does with a commanded-voltage recording). Default: the drive's own
      `inverter.u_dt` (an exact model); `0` gives the observer the raw commanded voltage.
      Three-phase drives only (a dual three-phase drive needs its x-y currents).

    The run's floating-point dtype is that of the `drive` and `controller` parameters
    (Python floats adapt): cast both with `pmsmjax.astype(..., jnp.float32)` for a
    single-precision run; inputs, initial values and the observer state follow.

    **Returns:** a `Trajectory`.
    """
    arguments = dict(locals())  # first statement: exactly the call's arguments
    check_drive_step(drive, T_s, solver, n_substeps)
    if observer is None or not isinstance(observer, AbstractObserver):
        raise ValueError(
            f"`observer` must be an `AbstractObserver` (e.g. `SensoredObserver()`); got "
            f"{type(observer).__name__}."
        )
    if scenario.observer_scale and not isinstance(observer.motor, PMSMParams):
        raise ValueError(
            "`Scenario(observer_scale=...)` needs an observer with a machine model "
            f"(`PMSMParams`); {type(observer).__name__}.motor is {observer.motor!r}."
        )
    N = scenario.n_steps(T_s)
    if not isinstance(save_every, int) or save_every < 1 or N % save_every:
        raise ValueError(
            f"`save_every` must be a positive integer dividing the number of steps {N}; "
            f"got {save_every!r}."
        )
    if key is None and is_concrete(sensing.noise_std) and np.any(
            np.asarray(sensing.noise_std) > 0):
        raise ValueError("`Sensing(noise_std > 0)` needs a PRNG `key` in `simulate`.")
    if getattr(controller, "startup", None) is not None and getattr(
            controller, "dual", None) is not None:
        raise ValueError("`FOC(startup=...)` (the I/f start) is not implemented with "
                         "dual three-phase current control (`FOC.dual`); use one or the "
                         "other.")
    if getattr(controller, "dual", None) is not None and not drive.dual:
        raise ValueError(
            f"`controller.dual` ({controller.dual.mode!r} control) needs a dual three-phase "
            f"drive; {drive.name!r} is three-phase.")

    if drive.dual and _compensates(drive, observer_u_dt):
        raise ValueError(
            "`simulate(observer_u_dt=...)`: dead-time compensation of the observer's voltage "
            "is modelled for three-phase drives only; pass `observer_u_dt=0` for a dual "
            "three-phase drive with `inverter.u_dt > 0`.")
    # Python numbers as initial values become arrays, so that a new initial state runs
    # the compiled program again instead of compiling another one (filter_jit treats
    # Python numbers as static); the run's dtype casts them inside
    units = {"theta0": "rad", "w_m0": "rad/s", "theta_hat0": "rad", "w_hat0": "rad/s",
             "i_dq0": "A"}
    for k in ("theta0", "w_m0", "theta_hat0", "w_hat0", "i_dq0"):
        v = arguments[k]
        if v is not None and is_concrete(v) and not np.all(np.isfinite(np.asarray(v))):
            raise NonFiniteInputError(f"`simulate({k}=...)` ({units[k]}) must be finite; "
                                      f"got {np.asarray(v).tolist()!r}.")
        if v is not None and is_concrete(v) and not isinstance(v, jax.Array):
            arguments[k] = np.asarray(v, dtype=np.float64)
    # The same for the parameters: a new value of a Python float in the drive, the
    # controller, the observer (a mismatched model, another design) or the measurement
    # chain (another noise level) runs the compiled program again
    # (pmsmjax._sim._batching.values_as_arrays; zeros stay Python numbers, which skip their
    # branch); checks that need the observer's concrete values run first
    observer.check_values(T_s)
    recheck((drive, controller))
    dtype = run_dtype(drive, controller)
    for k in ("drive", "controller", "observer", "sensing"):
        arguments[k] = values_as_arrays(arguments[k], dtype)
    arguments["drive"] = without_labels(arguments["drive"])
    return _simulate(arguments)


def _compensates(drive: Drive, observer_u_dt) -> bool:
    """Whether the observer's voltage is compensated for the inverter error (a static
    decision: False only when the model's `u_dt` is `None` or a Python zero)."""
    return not _is_zero(drive.inverter.u_dt if observer_u_dt is None else observer_u_dt)


@eqx.filter_jit
def _simulate(arguments: dict) -> Trajectory:
    """The jitted body of `simulate`, called with its (validated) arguments by name."""
    names = ("drive controller observer scenario T_s solver n_substeps sensing key theta0 "
             "w_m0 theta_hat0 w_hat0 i_dq0 save_every throw observer_u_dt").split()
    (drive, controller, observer, scenario, T_s, solver, n_substeps, sensing, key, theta0,
     w_m0, theta_hat0, w_hat0, i_dq0, save_every, throw, observer_u_dt) = (
        arguments[k] for k in names)
    compensate = _compensates(drive, observer_u_dt)
    u_dt_model = drive.inverter.u_dt if observer_u_dt is None else observer_u_dt
    # Validated by `simulate` (with concrete values, outside jit).
    N = scenario.n_steps(T_s)
    plant0 = PMSM(drive.motor, drive.mechanics, drive.inverter)
    # The run's floating dtype follows the drive and controller parameters (float32 after
    # `astype`); inputs and initial states are cast to it, and so is the carried state
    # after every step, so a float64 leaf elsewhere (e.g. an observer) cannot promote it.
    dtype = run_dtype(drive, controller)
    # The scenario's inputs and the current noise are evaluated inside the scan, from the
    # step index, so memory grows with the batch, not with batch x steps. The noise comes
    # in blocks of _NOISE_BLOCK steps (block j from `fold_in(key, j)`), drawn when a block
    # starts and carried: the same sequence whatever `save_every`, at the cost of one
    # random draw per block. (The step index is not batched, so under `vmap` the refill
    # stays a real branch.)
    T_s_ = jnp.asarray(T_s, dtype)

    def inputs_at(k):
        t_k = k.astype(dtype) * T_s_
        return t_k, cast_floats(scenario.sample(t_k), dtype)

    def noise_block(j):
        return sensing.noise_std * jr.normal(jr.fold_in(key, j), (_NOISE_BLOCK, 2), dtype)

    def noise_at(blk, k):
        blk = jax.lax.cond(k % _NOISE_BLOCK == 0, lambda: noise_block(k // _NOISE_BLOCK),
                           lambda: blk)
        return blk, blk[k % _NOISE_BLOCK]

    inputs0 = inputs_at(jnp.asarray(0))[1]

    y0 = cast_floats(plant0.init(theta0=theta0, w_m0=w_m0, i_dq0=i_dq0), dtype)
    if scenario.w_m_imposed is not None:
        y0 = eqx.tree_at(lambda y: y.w_m, y0, jnp.asarray(inputs0["w_m_imposed"], dtype))
    th_hat0 = y0.theta if theta_hat0 is None else jnp.asarray(theta_hat0, dtype)
    w_hat0_ = y0.w_m if w_hat0 is None else jnp.asarray(w_hat0, dtype)
    dual_ctrl = getattr(controller, "dual", None)
    u_zero = jnp.zeros(2 if dual_ctrl is None else 4, dtype)  # (+ x-y voltage)
    zero = jnp.zeros((), dtype)
    carry0 = dict(
        plant=split_state(y0),  # in component form (2-vectors as tuples)
        ctrl=cast_floats(controller.init(th_hat0) if getattr(controller, "startup", None)
                          is not None else controller.init(), dtype),
        obs=cast_floats(observer.init(theta0=th_hat0, w0=w_hat0_), dtype),
        u_prev=jnp.zeros(2, dtype),  # applied over [t_{k-1}, t_k)
        u_pending=u_zero,  # computed at k-1, applied over [t_k, t_{k+1}) if delayed
        i_hist=jnp.zeros((sensing.delay, 2), dtype),
        ok=jnp.array(True),
        ise=(zero, zero, zero),  # integrals of theta_err^2, (w_ref - w)^2, (w - w_hat)^2
        noise=None if key is None else jnp.zeros((_NOISE_BLOCK, 2), dtype),
        i_meas_prev=jnp.zeros(2, dtype) if compensate else None,
    )
    # under vmap, every carry batched from the start (pmsmjax._sim._batching: one pass of
    # the scan's batching fixpoint over the step instead of three or four)
    carry0 = batched_like(carry0, arguments)
    carry_dtypes = jax.tree_util.tree_map(lambda a: a.dtype, carry0)
    i_bound = 20.0 * drive.i_max
    w_bound = 20.0 * drive.w_rated
    speed_mode = scenario.speed_mode
    imposed = scenario.w_m_imposed is not None

    # The step works on vector components (x, y) where it can, and evaluates each sin/cos
    # once (`cos_sin`): XLA then compiles it to a few element-wise loops (see BENCHMARKS.md).
    def step(carry, k):
        t_k, inp = inputs_at(k)
        if key is None:
            n_k, noise_blk = None, carry["noise"]
        else:
            noise_blk, n_k = noise_at(carry["noise"], k)
        y = carry["plant"]
        if imposed:
            y = eqx.tree_at(lambda s: s.w_m, y, inp["w_m_imposed"])
        # --- sensing
        c, s = cos_sin(y.theta)
        i_d, i_q = y.i_dq
        i_ab_true = jnp.stack(_rotate(c, s, i_d, i_q), -1)  # inv_park(i_dq, theta)
        if sensing.delay > 0:
            i_samp = carry["i_hist"][0]
            i_hist = jnp.concatenate([carry["i_hist"][1:], i_ab_true[None]], 0)
        else:
            i_samp, i_hist = i_ab_true, carry["i_hist"]
        i_a, i_b = i_samp[..., 0], i_samp[..., 1]
        if n_k is not None:
            i_a, i_b = i_a + n_k[..., 0], i_b + n_k[..., 1]
        i_a = sensing.quantise(i_a, sensing.quantum)
        i_b = sensing.quantise(i_b, sensing.quantum)
        i_meas = jnp.stack([i_a, i_b], -1)
        theta_enc = sensing.quantise(y.theta, sensing.encoder_quantum)
        u_obs = carry["u_prev"]
        if compensate:  # no period before k = 0 (u_prev is zero there)
            u_obs = jnp.where(k > 0, observer_voltage(u_obs, carry["i_meas_prev"], i_meas,
                                                      u_dt_model, drive.inverter.i_dt), u_obs)
        meas = Measurement(i_ab=i_meas, u_ab=u_obs, theta=theta_enc, w_m=y.w_m)
        # --- observer
        obs = observer
        if inp["observer_scale"]:
            obs = eqx.tree_at(lambda o: o.motor, observer,
                              scale_motor(observer.motor, inp["observer_scale"]))
        obs_state, est = obs.step(carry["obs"], meas, T_s)
        # --- control in the estimated frame (or the start-up's frame while it runs)
        ctrl_carry, th_c, w_c = carry["ctrl"], est.theta_hat, est.w_hat
        if speed_mode and getattr(controller, "startup", None) is not None:
            ctrl_carry, th_c, w_c = controller.frame(ctrl_carry, th_c, w_c,
                                                     inp["w_m_ref"], T_s)
        adv = (0.5 + (1.0 if drive.inverter.delay else 0.0)) * w_c * T_s \
            if controller.angle_advance else 0.0
        u_xy_cmd = None
        if dual_ctrl is None:
            c_hat, s_hat = cos_sin(th_c)
            i_c = jnp.stack(_rotate(c_hat, -s_hat, i_a, i_b), -1)  # park(i_meas, th_c)
            ctrl_state, out = controller.step(
                ctrl_carry, i_c, w_c, inp["w_m_ref"], T_s,
                i_ref_override=jnp.stack([inp["i_d_ref"], inp["i_q_ref"]]),
                speed_mode=speed_mode,
            )
        else:  # dual three-phase current control (x-y sampled without `sensing`)
            ctrl_state, out, u_xy_cmd = dual_ctrl.step(
                controller, carry["ctrl"], i_meas, jnp.stack(y.i_xy, -1), est.theta_hat,
                est.theta_hat + adv, est.w_hat, inp["w_m_ref"], T_s,
                i_ref_override=jnp.stack([inp["i_d_ref"], inp["i_q_ref"]]),
                speed_mode=speed_mode,
            )
        c_u, s_u = cos_sin(th_c + adv)
        u_cmd = jnp.stack(_rotate(c_u, s_u, out.u_dq[..., 0], out.u_dq[..., 1]), -1)
        if u_xy_cmd is not None:  # the x-y voltage goes through the same inverter delay
            u_cmd = jnp.concatenate([u_cmd, u_xy_cmd], -1)
        if drive.inverter.delay:
            u_apply, u_pending = carry["u_pending"], u_cmd
        else:
            u_apply, u_pending = u_cmd, carry["u_pending"]
        u_xy_apply = None
        if u_xy_cmd is not None:
            u_apply, u_xy_apply = u_apply[..., :2], u_apply[..., 2:]
        # --- plant over [t_k, t_k+1)
        plant = plant0
        if inp["plant_scale"]:
            plant = PMSM(scale_motor(drive.motor, inp["plant_scale"]), drive.mechanics,
                         drive.inverter)
        args = PlantInput(u_ab=(u_apply[..., 0], u_apply[..., 1]), tau_L=inp["tau_L"],
                          u_xy=None if u_xy_apply is None else
                          (u_xy_apply[..., 0], u_xy_apply[..., 1]),
                          free=0.0 if imposed else 1.0)
        y_new = integrate(plant._rates, y, args, T_s, solver=solver, n_substeps=n_substeps)
        # diverged: the plant's state, or the observer's estimate (a speed estimate that
        # runs away while the torque limit keeps the rotor bounded), out of its bounds
        good = checkpoint_name(carry["ok"] & _finite_bounded(y_new, i_bound, w_bound)
                               & _estimate_bounded(est, w_bound), _OK_NAME)
        y_next = jax.tree_util.tree_map(lambda a, b: jnp.where(good, a, b), y_new, y)
        theta_err = wrap_angle(y.theta - est.theta_hat)
        ise = tuple(a + T_s * b for a, b in zip(carry["ise"], (
            theta_err ** 2, (inp["w_m_ref"] - y.w_m) ** 2, (y.w_m - est.w_hat) ** 2)))
        new_carry = dict(plant=y_next, ctrl=ctrl_state, obs=obs_state, u_prev=u_apply,
                         u_pending=u_pending, i_hist=i_hist, ok=good, ise=ise,
                         noise=noise_blk, i_meas_prev=i_meas if compensate else None)
        new_carry = jax.tree_util.tree_map(lambda a, d: jnp.asarray(a, d), new_carry,
                                           carry_dtypes)

        def record():
            u_a, u_b = u_apply[..., 0], u_apply[..., 1]
            rec = dict(
                t=t_k, theta=wrap_angle(y.theta), w_m=y.w_m, theta_hat=est.theta_hat,
                w_hat=est.w_hat, theta_err=theta_err, i_dq=jnp.stack(y.i_dq, -1),
                i_ab=i_ab_true,
                i_meas_ab=i_meas, u_ab=u_apply,
                u_dq=jnp.stack(_rotate(c, -s, u_a, u_b), -1),  # park(u_apply, theta)
                i_ref=out.i_ref, tau_ref=out.tau_ref, tau_M=plant.torque(join_state(y)),
                tau_L=inp["tau_L"], w_m_ref=inp["w_m_ref"], extras=est.extras,
            )
            if drive.dual:
                rec["i_xy"] = jnp.stack(y.i_xy, -1)
                rec["u_xy"] = jnp.zeros_like(u_apply) if u_xy_apply is None else u_xy_apply
            return cast_floats(rec, dtype)

        return new_carry, record

    # Reverse mode: each step is recomputed in the backward pass from the carry, keeping
    # only the per-step divergence flag; cheaper than storing the intermediate values
    # of every step (and far less memory).
    @functools.partial(jax.checkpoint, prevent_cse=False, policy=_CHECKPOINT_POLICY)
    def step_recorded(carry, x):
        new_carry, record = step(carry, x)
        return new_carry, record()

    steps = jnp.arange(N, dtype=jnp.int32)
    if save_every == 1:
        carry, rec = jax.lax.scan(step_recorded, carry0, steps)
    else:
        # Record the first sample of each chunk of `save_every` steps, so memory does not
        # grow with `save_every`. The program holds one instance of the step: every step
        # computes its record and the loop's carry keeps the one of the chunk's first
        # step (a select). Against a first step of its own followed by an unrecorded
        # loop, this compiles a quarter to a third faster (a closed-loop gradient under
        # quick compiles: half the time) for up to 8 % more run time; a `lax.cond` in
        # place of the select ran slower still (measured when it was chosen: the section
        # "One step per chunk" in `git log -p BENCHMARKS.md`).
        rec_shape = jax.eval_shape(lambda c: step(c, jnp.int32(0))[1](), carry0)
        slot0 = batched_like(
            jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), rec_shape), arguments)

        @functools.partial(jax.checkpoint, prevent_cse=False, policy=_CHECKPOINT_POLICY)
        def step_slot(cs, k):
            c, slot = cs
            new_c, record = step(c, k)
            first = k % save_every == 0
            slot = jax.tree_util.tree_map(lambda r, o: jnp.where(first, r, o), record(), slot)
            return (new_c, slot), None

        def chunk(c, k0):
            (c, r), _ = jax.lax.scan(step_slot, (c, slot0),
                                     k0 + jnp.arange(save_every, dtype=jnp.int32))
            return c, r

        carry, rec = jax.lax.scan(chunk, carry0, steps[::save_every])
    status = RESULTS.where(carry["ok"], RESULTS.successful, RESULTS.diverged)
    y_end = carry["plant"]
    traj = Trajectory(**rec, ise_theta=carry["ise"][0], ise_w=carry["ise"][1],
                      ise_w_hat=carry["ise"][2], status=status,
                      t_end=jnp.asarray(N, dtype) * T_s_, theta_end=wrap_angle(y_end.theta),
                      w_m_end=y_end.w_m, i_dq_end=jnp.stack(y_end.i_dq, -1))
    if throw:
        traj = eqx.error_if(
            traj, ~carry["ok"],
            "simulate: the run diverged (a state or the observer's estimate became "
            "non-finite or out of bounds); "
            "pass throw=False to get the status per run instead.")
    return traj
