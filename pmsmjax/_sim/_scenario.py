"""Declarative scenarios: piecewise-linear profiles of the external inputs.

A `Profile` is defined by breakpoints `(t_i, v_i)` with non-decreasing `t_i`; it is
linear between breakpoints, constant before the first and after the last, and a
repeated time is a step (the later value holds from that instant on). Inside the
simulation every input is sampled at the sampling instants t_k and held constant over
[t_k, t_{k+1}), so steps take effect exactly at sampling instants.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._validate import check_positive, is_concrete


class Profile(eqx.Module):
    """Piecewise-linear function of time (see module docstring).

    **Arguments:**

    - `t`: breakpoint times (s), non-decreasing, at least one.
    - `v`: values at the breakpoints (unit of the input it drives).
    """

    t: jnp.ndarray
    v: jnp.ndarray

    def __init__(self, t, v):
        t = np.asarray(t, dtype=float).reshape(-1) if is_concrete(t) else jnp.asarray(t)
        v = jnp.asarray(v).reshape(-1) if not is_concrete(v) else \
            np.asarray(v, dtype=float).reshape(-1)
        if t.shape != v.shape:
            raise ValueError(
                f"`Profile(t=..., v=...)` need the same number of breakpoints; got "
                f"{t.shape[0]} times and {v.shape[0]} values."
            )
        if t.shape[0] == 0:
            raise ValueError("`Profile(t=...)` is empty: give at least one breakpoint.")
        if is_concrete(t):
            if not np.all(np.isfinite(t)):
                raise ValueError(f"`Profile(t=...)` (s) must be finite; got {t}.")
            if np.any(np.diff(t) < 0):
                raise ValueError(
                    f"`Profile(t=...)` (s) must be non-decreasing (repeat a time for a "
                    f"step); got {t}."
                )
        if is_concrete(v) and not np.all(np.isfinite(np.asarray(v))):
            raise ValueError(f"`Profile(v=...)` must be finite; got {np.asarray(v)}.")
        self.t = jnp.asarray(t)
        self.v = jnp.asarray(v)

    @classmethod
    def constant(cls, value) -> Profile:
        return cls([0.0], [value])

    @classmethod
    def steps(cls, times, values, initial=0.0) -> Profile:
        """`initial` until `times[0]`, then `values[i]` from `times[i]` on (steps)."""
        times = np.asarray(times, dtype=float).reshape(-1)
        values = list(np.asarray(values, dtype=float).reshape(-1))
        t, v = [0.0], [float(initial)]
        prev = float(initial)
        for ti, vi in zip(times, values):
            t += [ti, ti]
            v += [prev, vi]
            prev = vi
        return cls(t, v)

    @classmethod
    def ramp(cls, t0, t1, v0, v1) -> Profile:
        """`v0` until `t0`, linear to `v1` at `t1`, then `v1`."""
        return cls([t0, t1], [v0, v1])

    def __call__(self, t):
        """Value at time(s) `t` (s); right-continuous at steps."""
        t = jnp.asarray(t)
        tb = self.t.astype(t.dtype) if jnp.issubdtype(t.dtype, jnp.floating) else self.t
        vb = self.v
        # index of the last breakpoint <= t (right-continuous at repeated times)
        k = jnp.searchsorted(tb, t, side="right") - 1
        n = tb.shape[0]
        k0 = jnp.clip(k, 0, n - 1)
        k1 = jnp.clip(k + 1, 0, n - 1)
        t0, t1 = tb[k0], tb[k1]
        v0, v1 = vb[k0], vb[k1]
        dt = t1 - t0
        frac = jnp.where(dt > 0, (t - t0) / jnp.where(dt > 0, dt, 1.0), 0.0)
        val = v0 + frac * (v1 - v0)
        return jnp.where(k < 0, vb[0], val)


_PARAM_NAMES = ("R_s", "L_d", "L_q", "psi_f")


class Scenario(eqx.Module):
    """External inputs of one closed-loop run.

    **Arguments:**

    - `t_end`: duration (s), > 0.
    - `w_m_ref`: speed reference (rad/s, electrical). `None` = current-controlled run,
      which then needs `i_d_ref` and `i_q_ref`.
    - `tau_L`: load torque (N m); default zero.
    - `i_d_ref`, `i_q_ref`: current references (A, controller frame) for current-controlled
      runs.
    - `w_m_imposed`: if given, a load machine imposes this electrical speed (rad/s) on the
      rotor (dynamometer test; the rotor's mechanical equation is then not integrated).
    - `plant_scale`: `{name: Profile}` multiplicative factors on plant machine parameters
      (`R_s`, `L_d`, `L_q`, `psi_f`), e.g. a resistance step from heating.
    - `observer_scale`: the same for the observer's machine model (mismatch steps).
    """

    t_end: float
    w_m_ref: Profile | None = None
    tau_L: Profile | None = None
    i_d_ref: Profile | None = None
    i_q_ref: Profile | None = None
    w_m_imposed: Profile | None = None
    plant_scale: dict | None = None
    observer_scale: dict | None = None

    def __check_init__(self):
        check_positive("Scenario", "t_end", self.t_end, "s")
        if self.w_m_ref is None and (self.i_d_ref is None or self.i_q_ref is None):
            raise ValueError(
                "`Scenario` needs either `w_m_ref` (speed control) or both `i_d_ref` and "
                "`i_q_ref` (current control)."
            )
        for field in ("plant_scale", "observer_scale"):
            d = getattr(self, field)
            if d is None:
                continue
            for name, prof in d.items():
                if name not in _PARAM_NAMES:
                    raise ValueError(
                        f"`Scenario({field}=...)` key {name!r} is not a machine parameter; "
                        f"allowed: {', '.join(_PARAM_NAMES)}."
                    )
                if not isinstance(prof, Profile):
                    raise ValueError(
                        f"`Scenario({field}[{name!r}])` must be a `Profile`; got "
                        f"{type(prof).__name__}."
                    )
                if is_concrete(prof.v) and np.any(np.asarray(prof.v) <= 0):
                    raise ValueError(
                        f"`Scenario({field}[{name!r}])` scale factors must be > 0; got "
                        f"{np.asarray(prof.v)}."
                    )
        for name in ("w_m_ref", "tau_L", "i_d_ref", "i_q_ref", "w_m_imposed"):
            p = getattr(self, name)
            if p is not None and not isinstance(p, Profile):
                raise ValueError(
                    f"`Scenario({name}=...)` must be a `Profile`; got {type(p).__name__}."
                )

    @property
    def speed_mode(self) -> bool:
        return self.w_m_ref is not None

    def n_steps(self, T_s) -> int:
        """Number of sampling periods of length `T_s` (s) in `t_end`."""
        n = int(round(float(self.t_end) / float(T_s)))
        if n < 1:
            raise ValueError(
                f"`Scenario(t_end={float(self.t_end):.6g})` s is shorter than one sampling "
                f"period T_s={float(T_s):.6g} s."
            )
        return n

    def sample(self, t):
        """All inputs at the sampling instants `t` (s) as a dict of arrays."""
        zero = jnp.zeros_like(t)
        out = {
            "w_m_ref": self.w_m_ref(t) if self.w_m_ref is not None else zero,
            "tau_L": self.tau_L(t) if self.tau_L is not None else zero,
            "i_d_ref": self.i_d_ref(t) if self.i_d_ref is not None else zero,
            "i_q_ref": self.i_q_ref(t) if self.i_q_ref is not None else zero,
            "w_m_imposed": self.w_m_imposed(t) if self.w_m_imposed is not None else zero,
            "plant_scale": {k: p(t) for k, p in (self.plant_scale or {}).items()},
            "observer_scale": {k: p(t) for k, p in (self.observer_scale or {}).items()},
        }
        return out
