"""The least-squares problem of `identify` (`_identify`): the unknowns (the named
parameters, and a load torque per segment where fitted), the segments' starts eliminated
by variable projection (`Problem.projected`), and the two compiled programs of the
fit: the Levenberg-Marquardt solve (`solve`, once per stage) and what the result needs
at the solution (`final`: the Jacobian for the covariance, the residuals per channel,
the model's response)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

from .._plant._motor import PMSM
from .._plant._params import Drive, Inverter
from . import _identify_saturation as _sat
from ._identifiable import SATURATION_FIT
from ._identify_motion import simulate_segments, with_loads, with_start


MOTOR = ("R_s", "L_d", "L_q", "psi_f")
MECH = ("J", "B")


def _with_values(drive: Drive, values: dict) -> Drive:
    """`drive` with traced parameter values replaced (no validation: inside the fit)."""
    for name, v in values.items():
        if name in MOTOR:
            drive = eqx.tree_at(lambda d, n=name: getattr(d.motor, n), drive, v)
        elif name in MECH:
            drive = eqx.tree_at(lambda d, n=name: getattr(d.mechanics, n), drive, v)
        elif name in SATURATION_FIT:
            continue  # set on the magnetic model (`Problem.plant`)
        else:  # u_dt, i_dt
            inv = {k: getattr(drive.inverter, k) for k in ("u_dc", "u_max", "delay", "u_dt",
                                                           "i_dt")}
            drive = eqx.tree_at(lambda d: d.inverter, drive, Inverter(**{**inv, name: v}))
    return drive


class Problem(eqx.Module):
    drive: Drive
    names: tuple = eqx.field(static=True)
    p0: jnp.ndarray  # initial values (SI)
    lin_scale: jnp.ndarray  # scale of the linear (u_dt) parameters, 0 for log ones
    commanded: bool = eqx.field(static=True)
    n_substeps: int = eqx.field(static=True)
    saturation: object = None  # the starting AlgebraicSaturation of a saturation fit
    measured: bool = eqx.field(static=True, default=False)  # the rotor moves as recorded
    # after the named unknowns in x, recording by recording, the constant load torque of
    # each segment where `fit_load` (in units of `load_scale`, N m); each segment's start
    # is not in x: `projected` eliminates it (offsets from the measured current in units
    # of `i_scale`, A, and, with the mechanics integrated, speed in `w_scale`, rad/s)
    n_seg: tuple = eqx.field(static=True, default=())
    fit_load: tuple = eqx.field(static=True, default=())
    load_scale: float = eqx.field(static=True, default=1.0)
    i_scale: float = eqx.field(static=True, default=1.0)
    w_scale: float = eqx.field(static=True, default=1.0)

    def values(self, x):
        k = len(self.names)
        vals = jnp.where(self.lin_scale > 0, self.p0 + self.lin_scale * x[:k],
                         self.p0 * jnp.exp(x[:k]))
        return dict(zip(self.names, [vals[j] for j in range(k)]))

    def slices(self) -> list:
        """Per recording, the slice of x that holds its segments' load torques, or None."""
        out, k = [], len(self.names)
        for n, f in zip(self.n_seg, self.fit_load):
            out.append(slice(k, k + n) if f else None)
            k += n if f else 0
        return out

    def n_unknowns(self) -> int:
        """The unknowns in x (the named parameters and the fitted loads)."""
        return len(self.names) + sum(n for n, f in zip(self.n_seg, self.fit_load) if f)

    @property
    def n_start(self) -> int:
        """The unknowns of each segment's start: its current, and speed if integrated."""
        return 2 if self.measured else 3

    def magnetic(self, x):
        """The `AlgebraicSaturation` at `x` (traced: derivatives flow through it)."""
        return _sat.with_values(self.saturation, self.values(x))

    def plant(self, x) -> PMSM:
        d = _with_values(self.drive, self.values(x))
        if self.saturation is not None:
            d = _sat.set_magnetic(d, self.magnetic(x))
        return PMSM(d.motor, d.mechanics, d.inverter if self.commanded else None)

    def simulate(self, plant, seg, start):
        """Model current (n, m, 2) and speed (n, m) of the segments `seg` started at the
        offsets `start` (n, n_start) from their measured states."""
        seg = with_start(seg, self.i_scale * start[:, :2],
                         None if self.measured else self.w_scale * start[:, 2])
        if self.saturation is not None:  # the flux-linkage form of the same plant
            return _sat.simulate_segments(plant, plant.motor.magnetic, seg, self.n_substeps,
                                          self.measured)
        return simulate_segments(plant, seg, self.n_substeps, self.measured)

    def _segment_residuals(self, plant, seg, start, sig_i, sig_w):
        """(n, R) weighted residuals of the segments `seg` from the offsets `start`."""
        n = seg.w0.shape[0]
        i_m, w_m = self.simulate(plant, seg, start)
        parts = [((i_m - seg.i_meas) / sig_i).reshape(n, -1)]
        if not self.measured:  # a recorded speed is an input, not a residual
            parts.append(((w_m - seg.w_meas) / sig_w).reshape(n, -1))
        return jnp.concatenate(parts, axis=1)

    def _loaded(self, x, segs) -> list:
        return [seg if load is None else with_loads(seg, self.load_scale * x[load])
                for seg, load in zip(segs, self.slices())]

    def start_directions(self, x, segs, sig_i, sig_w) -> list:
        """Per recording, S (n, R, n_start): the derivative of each segment's weighted
        residuals with respect to its start, at `x` (held: no derivative flows through
        it). One derivative direction per start component, on `n_start` copies of the
        segments side by side (a single forward-mode pass over the batch: tracing a
        `vmap` over directions through the segments' loop costs seconds more)."""
        x = jax.lax.stop_gradient(x)
        plant, out, k = self.plant(x), [], self.n_start
        for seg in self._loaded(x, segs):
            n = seg.w0.shape[0]
            copies = jax.tree_util.tree_map(
                lambda a: jnp.concatenate([a] * k) if eqx.is_array(a) else a, seg)
            dirs = jnp.repeat(jnp.eye(k, dtype=x.dtype), n, axis=0)  # (k n, k)
            S = jax.jvp(lambda d, c=copies: self._segment_residuals(plant, c, d, sig_i, sig_w),
                        (jnp.zeros_like(dirs),), (dirs,))[1]
            out.append(jnp.moveaxis(S.reshape(k, n, -1), 0, -1))
        return out

    def projected(self, x, segs, sig_i, sig_w, directions=None) -> list:
        """Per recording, `(r, start)`: each segment's weighted residuals (n, R: currents,
        then speeds if integrated) at its fitted start `start` (n, n_start).

        Variable projection: with the parameters fixed, the residuals of a segment are
        nearly affine in its start (exactly so for the constant-inductance plant on the
        recorded speed), so one Gauss-Newton step from the measured start, r0 + S d with
        d = -(S^T S)^-1 S^T r0, minimises them over it (S: the residuals' derivative with
        respect to the start). S is computed with the parameters held (no derivative
        flows through it: the Jacobian of the projected residuals is then P J, Kaufman's
        approximation, exact at the minimum), from `n_start` derivative directions shared
        by all segments (each segment's residuals depend on its own start only). The
        parameters' Gauss-Newton covariance from these residuals is their covariance with
        the starts unknown, and the least-squares problem keeps only the named
        parameters and the loads."""
        plant = self.plant(x)
        if directions is None:
            directions = self.start_directions(x, segs, sig_i, sig_w)
        out = []
        for seg, S in zip(self._loaded(x, segs), directions):
            zero = jnp.zeros((seg.w0.shape[0], self.n_start), x.dtype)
            r0 = self._segment_residuals(plant, seg, zero, sig_i, sig_w)
            start = -jnp.linalg.solve(jnp.einsum("nri,nrj->nij", S, S),
                                      jnp.einsum("nri,nr->ni", S, r0)[..., None])[..., 0]
            out.append((r0 + jnp.einsum("nri,ni->nr", S, start), start))
        return out

    def residuals(self, x, args):
        """`args`: the segments, the weights and the start directions (None: at x)."""
        segs, sig_i, sig_w, directions = args
        return jnp.concatenate([r.ravel() for r, _ in self.projected(x, segs, sig_i, sig_w,
                                                                     directions)])


    def channel_rms(self, x, segs, sig_i, sig_w, projected) -> tuple:
        """RMS of the current (A) and speed (rad/s; 0 on the recorded speed) residuals of
        `projected` (`Problem.projected` at x)."""
        sq_i, sq_w, n_i, n_w = 0.0, 0.0, 0, 0
        for seg, (r, _) in zip(segs, projected):
            n_cur = seg.i_meas[0].size
            sq_i, n_i = sq_i + jnp.sum((sig_i * r[:, :n_cur]) ** 2), n_i + r[:, :n_cur].size
            sq_w, n_w = sq_w + jnp.sum((sig_w * r[:, n_cur:]) ** 2), n_w + seg.w_meas.size
        return jnp.sqrt(sq_i / n_i), 0.0 * sq_w if self.measured else jnp.sqrt(sq_w / n_w)


class Solved(eqx.Module):
    """What `solve` returns: the solution, optimistix's result code, its steps and the
    residuals' RMS per channel there (current in A, speed in rad/s)."""
    value: jnp.ndarray
    result: jnp.ndarray  # the integer behind `optx.RESULTS`
    steps: jnp.ndarray
    rms_i: jnp.ndarray
    rms_w: jnp.ndarray


class Final(eqx.Module):
    """What `final` returns: the weighted residuals, their Jacobian, the RMS per channel
    and per recording the model's (current, speed) response."""
    r: jnp.ndarray
    jacobian: jnp.ndarray
    rms_i: jnp.ndarray
    rms_w: jnp.ndarray
    model: list


def _stored(tag, program, jitted, args, out_type):
    """`program(*args)` as a stored program (`pmsmjax.runtime.stored_call`: a repeated
    command skips the tracing, about ten seconds for the solve) or, where none can be
    stored (the cache off, under a transformation), by its `equinox.filter_jit` form
    `jitted`."""
    from .. import runtime

    out = runtime.stored_call(tag, program, args, out_type)
    return jitted(*args) if out is None else out


def _solve_program(problem, x0, args, rtol, atol, max_steps) -> Solved:
    # the segments' start directions held at x0 over the solve (the final covariance and
    # residuals take them at the solution): each step then integrates the segments once
    # with the parameters' derivatives and not again for the directions; from the first
    # stage's solution they differ from those at the final one by the small step between
    args = (*args[:3], problem.start_directions(x0, *args[:3]))
    sol = optx.least_squares(problem.residuals, optx.LevenbergMarquardt(rtol=rtol, atol=atol),
                             x0, args=args, max_steps=max_steps, throw=False)
    rms = problem.channel_rms(sol.value, *args[:3], problem.projected(sol.value, *args))
    return Solved(sol.value, sol.result._value, sol.stats["num_steps"], *rms)


solve_jit = eqx.filter_jit(_solve_program)


def solve(problem, x0, args, rtol, atol, max_steps):
    """The Levenberg-Marquardt solve from x0 with the weights of `args` (segments, sig_i,
    sig_w): the solution, optimistix's result, its steps and the residuals' RMS per
    channel there (the weights of a next stage)."""
    out = _stored("identify-solve", _solve_program, solve_jit,
                  (problem, x0, args, float(rtol), float(atol), int(max_steps)), Solved)
    result = eqx.tree_at(lambda r: r._value, optx.RESULTS.successful, out.result)
    return out.value, result, out.steps, out.rms_i, out.rms_w


def _final_program(problem, x, args) -> Final:
    segs, sig_i, sig_w = args
    held = (*args, problem.start_directions(x, *args))  # at x, held
    projected = problem.projected(x, *held)
    r = jnp.concatenate([p[0].ravel() for p in projected])
    plant, model = problem.plant(x), []
    for seg, load, (_, start) in zip(segs, problem.slices(), projected):
        if load is not None:
            seg = with_loads(seg, problem.load_scale * x[load])
        model.append(problem.simulate(plant, seg, start))
    return Final(r, jax.jacfwd(problem.residuals)(x, held),
                 *problem.channel_rms(x, segs, sig_i, sig_w, projected), model)


final_jit = eqx.filter_jit(_final_program)


def final(problem, x, args):
    """At the solution x, one compiled program: the weighted residuals and their Jacobian
    (for the covariance), the RMS per channel and the model's response per recording
    from its segments' fitted starts (the traces of the result)."""
    out = _stored("identify-final", _final_program, final_jit, (problem, x, args), Final)
    return out.r, out.jacobian, out.rms_i, out.rms_w, out.model
