"""What the rotor and the sensors of a recording give identification (`_identify`): the
recordings cut into multiple-shooting segments (`Segments`, `cut`) and simulated
(`simulate_segments`), the rotor's motion in the model (`mechanics_mode`, `motion_step`:
measured or integrated), the load torque that drives integrated mechanics (`load_mode`,
`with_loads`: recorded or fitted per segment) and the current noise the recordings imply
(`current_noise`)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._frames import park
from .._plant._motor import PMSM, PlantInput, PlantState, cos_sin
from .._sim._integrate import RK4, integrate
from ._recording import SPEED_WINDOW, RecordedData, centred_speed


class IdentifyError(ValueError):
    """A fitted parameter the recording(s) cannot determine, or unusable data."""


def mechanics_mode(names: Sequence[str], mechanics: str = "auto") -> str:
    """The rotor motion `identify` uses for the fitted `names`: `"measured"` or
    `"integrated"` (`mechanics` "auto": integrated when J or B is fitted)."""
    mech_fit = [n for n in names if n in ("J", "B")]
    if mechanics not in ("auto", "measured", "integrated"):
        raise IdentifyError(f"`identify(mechanics=...)` must be 'auto', 'measured' or "
                            f"'integrated'; got {mechanics!r}.")
    if mechanics == "measured" and mech_fit:
        raise IdentifyError(
            f"`identify(mechanics='measured')` runs the model on the recorded speed, so "
            f"{', '.join(mech_fit)} cannot act on it; fit them with "
            f"mechanics='integrated' (or 'auto') and a logged load torque.")
    if mechanics == "auto":
        return "integrated" if mech_fit else "measured"
    return mechanics


def recorded_speed(r: RecordedData) -> np.ndarray:
    """The recorded speed, or the unwrapped angle's centred difference over 2 ms (as
    `pmsmjax convert` derives a speed from an encoder column: an encoder's quantum
    divided by 2 ms, not by one period)."""
    if r.w_m is not None:
        return np.asarray(r.w_m, float)
    return centred_speed(np.unwrap(np.asarray(r.theta, float)), np.asarray(r.t, float),
                         SPEED_WINDOW)


class Segments(eqx.Module):
    """One recording cut into `n` segments of `m` steps (arrays; the plant's inputs)."""

    i0_ab: jnp.ndarray  # (n, 2) measured current at each segment's start
    th0: jnp.ndarray  # (n,)
    w0: jnp.ndarray  # (n,)
    u: jnp.ndarray  # (n, m, 2) voltage over each step
    tau_L: jnp.ndarray  # (n, m)
    i_meas: jnp.ndarray  # (n, m, 2) measured current after each step
    w_meas: jnp.ndarray  # (n, m)
    th: jnp.ndarray  # (n, m) measured angle at each step's start
    w: jnp.ndarray  # (n, m) measured speed at each step's start
    acc: jnp.ndarray  # (n, m) measured speed change over each step / T_s
    T_s: float = eqx.field(static=True)


def cut(r: RecordedData, m: int) -> Segments:
    n = (r.n - 1) // m
    idx = np.arange(n) * m
    steps = idx[:, None] + np.arange(m)[None, :]
    w = recorded_speed(r)
    tau = np.zeros(r.n) if r.tau_L is None else np.asarray(r.tau_L, float)
    return Segments(
        i0_ab=jnp.asarray(r.i_ab[idx]), th0=jnp.asarray(np.asarray(r.theta)[idx]),
        w0=jnp.asarray(w[idx]), u=jnp.asarray(r.u_ab[steps]), tau_L=jnp.asarray(tau[steps]),
        i_meas=jnp.asarray(r.i_ab[steps + 1]), w_meas=jnp.asarray(w[steps + 1]),
        th=jnp.asarray(np.asarray(r.theta, float)[steps]), w=jnp.asarray(w[steps]),
        acc=jnp.asarray((w[steps + 1] - w[steps]) / r.T_s), T_s=float(r.T_s))


def simulate_segments(plant: PMSM, seg: Segments, n_substeps: int, measured: bool):
    """Model current (n, m, 2) and speed (n, m) after each step of each segment;
    `measured`: the rotor moves as recorded (module docstring), else its mechanics are
    integrated."""

    def one(i0, th0, w0, u, tau, th, w, acc):
        c, s = cos_sin(th0)
        y0 = PlantState(i_dq=jnp.stack([c * i0[0] + s * i0[1], c * i0[1] - s * i0[0]]),
                        theta=th0, w_m=w0)

        def step(y, x):
            uk, tk, thk, wk, ak = x
            y, field, args = motion_step(plant.vector_field, y, PlantInput(u_ab=uk, tau_L=tk),
                                         thk, wk, ak, measured)
            y = integrate(field, y, args, seg.T_s, solver=RK4(), n_substeps=n_substeps)
            return y, (plant.i_ab(y), y.w_m)

        return jax.lax.scan(step, y0, (u, tau, th, w, acc))[1]

    return jax.vmap(one)(seg.i0_ab, seg.th0, seg.w0, seg.u, seg.tau_L, seg.th, seg.w, seg.acc)


LOAD_MODES = ("auto", "recorded", "segment")


def load_mode(recs: Sequence[RecordedData], mechanics: str, load: str = "auto") -> tuple:
    """Per recording, whether `identify` fits a constant load torque per segment
    (`True`) or drives the integrated mechanics with the recorded one (zero where none is
    logged). `load`: `"segment"` fits one for every recording (added to a logged load
    torque: what the log misses, e.g. friction or a torque sensor's offset), `"recorded"`
    fits none, `"auto"` fits one where a recording logs no load torque. With the rotor
    moving as measured no load acts on the model: only `"auto"` and `"recorded"` apply."""
    if load not in LOAD_MODES:
        raise IdentifyError(f"`identify(load=...)` must be one of "
                            f"{', '.join(map(repr, LOAD_MODES))}; got {load!r}.")
    if mechanics == "measured":
        if load == "segment":
            raise IdentifyError(
                "`identify(load='segment')` fits a load torque per segment, which acts only "
                "on integrated mechanics; with mechanics='measured' the model runs on the "
                "recorded speed and needs no load (fit J or B, or pass "
                "mechanics='integrated').")
        return tuple(False for _ in recs)
    if load == "segment":
        return tuple(True for _ in recs)
    if load == "recorded":
        return tuple(False for _ in recs)
    return tuple(r.tau_L is None for r in recs)


def with_loads(seg: Segments, tau: jnp.ndarray) -> Segments:
    """`seg` with the constant load torque `tau[j]` (N m) added over segment j."""
    return eqx.tree_at(lambda s: s.tau_L, seg, seg.tau_L + tau[:, None])


def with_start(seg: Segments, di_ab: jnp.ndarray, dw: jnp.ndarray | None) -> Segments:
    """`seg` whose segments start from the measured current plus `di_ab` (n, 2; A) and,
    unless None, the measured speed plus `dw` (n; rad/s): the fitted start states."""
    seg = eqx.tree_at(lambda s: s.i0_ab, seg, seg.i0_ab + di_ab)
    return seg if dw is None else eqx.tree_at(lambda s: s.w0, seg, seg.w0 + dw)


def motion_step(field, y, args, theta, w_m, acc, measured: bool):
    """One step's `(state, vector field, its args)`: unchanged when the rotor's
    mechanics are integrated; when it moves as `measured`, the state (any module with
    `theta`, `w_m`) takes the recorded angle (rad) and speed (rad/s) and the field turns
    it at the constant acceleration `acc` (rad/s^2) instead of the mechanical equation."""
    if not measured:
        return y, field, args

    def moved(t, v, a):
        rates = field(t, v, a)
        return eqx.tree_at(lambda r: r.w_m, rates, acc + 0.0 * rates.w_m)

    y = eqx.tree_at(lambda v: (v.theta, v.w_m), y, (theta, w_m))
    return y, moved, eqx.tree_at(lambda a: a.free, args, 0.0)


def current_noise(recs: Sequence[RecordedData]) -> float:
    """The current noise (A, one standard deviation per component) the recordings imply:
    1.4826 x the median absolute second difference of the measured currents in rotor
    coordinates (recorded angle), over sqrt(6). White noise of standard deviation sigma
    gives sigma; a current that is smooth over three samples adds little, and steps are
    outliers the median ignores."""
    d2 = []
    for r in recs:
        i_dq = np.asarray(park(np.asarray(r.i_ab, float), np.asarray(r.theta, float)))
        d2.append((i_dq[2:] - 2.0 * i_dq[1:-1] + i_dq[:-2]).ravel())
    d2 = np.concatenate(d2)
    return float(1.4826 * np.median(np.abs(d2)) / math.sqrt(6.0))
