r"""Tunable ESO gain schedules: unconstrained variables <-> physical design parameters.

The observer gains of zhang2022 follow from six design quantities at each operating speed
$\omega_0$ (Sec. III; `pmsmjax.observers.eso_gains`):

- flux poles (16)-(17): damping $\zeta_1$ (-) and the ratio $\rho = \omega_1/|\omega_0|$
  (-), so that $\omega_1 = \rho|\omega_0|$ (the axes of Fig. 1);
- speed/angle poles (18)-(19): damping $\zeta_2$ (-) and bandwidth $\omega_2$ (rad/s);
- the null-space components of (19) beyond the minimum-norm solution (25), as
  dimensionless multiples $\nu_2$, $\nu_3$ of the minimum-norm gain sizes:
  $n_2 = \nu_2\, 2\zeta_2\omega_2/|\psi_{a0}|$, $n_3 = \nu_3\,\omega_2^2/|\psi_{a0}|$.

`GainSchedule` writes them as the paper's design times smooth corrections over speed
$s = |\omega_0|/\omega_r$:

$$\zeta_1 = (1.5 + s)\,c_{\zeta_1}(s),\quad \rho = \frac{1.5}{1.5 + s}\,c_\rho(s),\quad
\zeta_2 = c_{\zeta_2}(s),\quad \omega_2 = \omega_{2,p}\,c_{\omega_2}(s),\quad
\nu_2(s),\ \nu_3(s),$$

so that all corrections $c = 1$ and $\nu = 0$ is exactly (38) with the minimum-norm gains
(25) at bandwidth $\omega_{2,p}$ and $\zeta_2 = 1$ (`paper`). Each correction is given at
a few speed nodes and interpolated (piecewise linear in $s$, in $\log c$; constant
outside the nodes), so the gains are a continuous function of the observer's own speed
estimate, as the paper's adaptive gains are.

**Positivity by reparameterisation** (the diffrax Kalman-filter example learns a matrix
root so that Q stays positive definite): the stored leaves are unconstrained reals $z$,
mapped into the open box `Bounds` gives,

$$c = c_{lo}\,(c_{hi}/c_{lo})^{\sigma(z)}\ \text{(the four factors)},\qquad
\nu = \nu_{lo} + (\nu_{hi} - \nu_{lo})\,\sigma(z),$$

with $\sigma$ the logistic function. Every $z \in \mathbb{R}$ gives a physical design
(positive bandwidths and damping, gains small enough for the sampling rate), and the
optimisers work on $z$ without constraints.

**Which leaves are tuned** is chosen by filtering the PyTree, not by lists of arrays:
`filter_spec(schedule, names)` builds a PyTree of booleans with `eqx.tree_at`, and
`eqx.partition(schedule, spec)` / `eqx.combine` split and rebuild it.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from pmsmjax.observers import AbstractGainSchedule, eso_gains, gains_pi, psi_a


#: Design quantities of `GainSchedule`, in the order they are reported.
TUNABLE = ("zeta1", "ratio", "zeta2", "w2", "nu2", "nu3")

#: Quantities written as positive factors on the paper's design; the others are signed.
_FACTORS = ("zeta1", "ratio", "zeta2", "w2")

_UNITS = {"zeta1": "-", "ratio": "-", "zeta2": "-", "w2": "rad/s", "nu2": "-", "nu3": "-"}


class Bounds(eqx.Module):
    """Open box of each tunable quantity, as `(lo, hi)` pairs.

    - `zeta1`, `ratio`, `zeta2`, `w2`: factors on the paper's values (38)/(25) (-);
      they need `0 < lo < 1 < hi` (the paper's design lies inside).
    - `nu2`, `nu3`: null-space components of (19) relative to (25) (-; signed), need
      `lo < 0 < hi`.

    The defaults (factors 1/5 .. 5) keep the discrete observer well inside its stability
    limit at 8 kHz for `zhang750` ($\\omega_2 T_s \\le 0.2$, and
    $\\rho|\\omega_0| T_s \\le 0.5$ up to rated speed).
    """

    zeta1: tuple[float, float] = (0.2, 5.0)
    ratio: tuple[float, float] = (0.2, 5.0)
    zeta2: tuple[float, float] = (0.2, 5.0)
    w2: tuple[float, float] = (0.2, 5.0)
    nu2: tuple[float, float] = (-1.5, 1.5)
    nu3: tuple[float, float] = (-1.5, 1.5)

    def __check_init__(self):
        for name in TUNABLE:
            b = getattr(self, name)
            try:
                lo, hi = (float(v) for v in b)
            except (TypeError, ValueError):
                raise ValueError(
                    f"`Bounds({name}=...)` must be a pair (lo, hi) of numbers; got {b!r}."
                ) from None
            if not (math.isfinite(lo) and math.isfinite(hi)) or not lo < hi:
                raise ValueError(
                    f"`Bounds({name}=...)` must be finite with lo < hi; got ({lo!r}, {hi!r})."
                )
            if name in _FACTORS and not 0 < lo < 1 < hi:
                raise ValueError(
                    f"`Bounds({name}=...)` is a factor on the paper's {name} and must satisfy "
                    f"0 < lo < 1 < hi (positive, so damping and bandwidths stay > 0; "
                    f"containing 1, the paper's design); got ({lo!r}, {hi!r})."
                )
            if name not in _FACTORS and not lo < 0 < hi:
                raise ValueError(
                    f"`Bounds({name}=...)` must contain 0 (lo < 0 < hi) so that the "
                    f"minimum-norm gains (25) are inside the box; got ({lo!r}, {hi!r})."
                )

    def to_physical(self, name: str, z):
        """Unconstrained `z` -> the factor (or `nu`) of quantity `name`, inside the box."""
        lo, hi = getattr(self, name)
        u = jax.nn.sigmoid(z)
        if name in _FACTORS:
            return lo * jnp.exp(u * jnp.log(hi / lo))
        return lo + (hi - lo) * u

    def to_unconstrained(self, name: str, x):
        """Inverse of `to_physical` (`x` strictly inside the box, else `ValueError`)."""
        lo, hi = getattr(self, name)
        x = np.asarray(x, dtype=float)
        if np.any(~np.isfinite(x)) or np.any(x <= lo) or np.any(x >= hi):
            raise ValueError(
                f"`{name}` {'factor ' if name in _FACTORS else ''}{x} lies outside the open "
                f"box ({lo:g}, {hi:g}) of `Bounds({name}=...)`; widen the bounds."
            )
        u = np.log(x / lo) / math.log(hi / lo) if name in _FACTORS else (x - lo) / (hi - lo)
        return np.log(u) - np.log1p(-u)


def paper_values(s, w2_paper):
    """The paper's design (38)/(25) at speed(s) `s` = |w0|/w_rated (p.u.):
    `{name: array}` with `w2 = w2_paper` (rad/s), `zeta2 = 1`, `nu2 = nu3 = 0`."""
    s = jnp.abs(jnp.asarray(s, dtype=float))
    zeta1 = 1.5 + s
    one = jnp.ones_like(s)
    return dict(zeta1=zeta1, ratio=1.5 / zeta1, zeta2=one, w2=w2_paper * one,
                nu2=0.0 * s, nu3=0.0 * s)


class GainSchedule(AbstractGainSchedule):
    r"""Smooth, tunable ESO gain schedule over speed (see the module docstring).

    Use it as the `design` of `ESOObserver`, `LESOObserver` or `AFOObserver`. The gains at
    an operating point are `eso_gains(psi_a(motor, i_dq), w0, zeta1, ratio |w0|, zeta2,
    w2, n2=..., n3=...)` with the quantities of `values(|w0| / w_rated)`; `pi` gives the
    AFO's speed law (53) from `zeta2`, `w2`.

    **Arguments:**

    - `s_nodes`: speed nodes $|\omega_0|/\omega_r$ (p.u.), strictly increasing, >= 1 node.
    - `w_rated`: rated electrical speed $\omega_r$ (rad/s).
    - `w2_paper`: the paper's speed/angle bandwidth $\omega_{2,p}$ (rad/s).
    - `z_zeta1`, `z_ratio`, `z_zeta2`, `z_w2`, `z_nu2`, `z_nu3`: unconstrained node values,
      shape `(n_nodes,)` each (build with `paper` or `from_values`).
    - `bounds`: the `Bounds` that map them to factors and `nu`.
    """

    s_nodes: jnp.ndarray
    w_rated: float
    w2_paper: float
    z_zeta1: jnp.ndarray
    z_ratio: jnp.ndarray
    z_zeta2: jnp.ndarray
    z_w2: jnp.ndarray
    z_nu2: jnp.ndarray
    z_nu3: jnp.ndarray
    bounds: Bounds

    def __check_init__(self):
        s = self.s_nodes
        if not isinstance(s, jax.core.Tracer):
            s = np.asarray(s, dtype=float)
            if s.ndim != 1 or s.size == 0 or np.any(~np.isfinite(s)) or np.any(s < 0) \
                    or np.any(np.diff(s) <= 0):
                raise ValueError(
                    "`GainSchedule(s_nodes=...)` (p.u. of rated speed) must be a non-empty, "
                    f"strictly increasing 1-D array of finite values >= 0; got {s}."
                )

    @classmethod
    def paper(cls, w_rated, s_nodes, w2_paper=2 * math.pi * 50.0,
              bounds: Bounds | None = None) -> GainSchedule:
        """The paper's design (38)/(25) (all corrections 1, `nu = 0`): the tuner's start."""
        s = np.asarray(s_nodes, dtype=float).reshape(-1)
        return cls.from_factors(s, w_rated, w2_paper, {}, bounds)

    @classmethod
    def from_factors(cls, s_nodes, w_rated, w2_paper, factors: dict,
                     bounds: Bounds | None = None) -> GainSchedule:
        """Build from node values of the corrections `{name: value or (n_nodes,)}`
        (factors for zeta1, ratio, zeta2, w2; `nu2`, `nu3` as they are); missing ones
        are 1 (factors) or 0 (`nu`)."""
        bounds = Bounds() if bounds is None else bounds
        s = np.asarray(s_nodes, dtype=float).reshape(-1)
        unknown = [n for n in factors if n not in TUNABLE]
        if unknown:
            raise ValueError(f"unknown quantities {unknown}; choose from {TUNABLE}.")
        z = {}
        for n in TUNABLE:
            x = factors.get(n, 1.0 if n in _FACTORS else 0.0)
            x = np.broadcast_to(np.asarray(x, dtype=float), s.shape)
            z[f"z_{n}"] = jnp.asarray(bounds.to_unconstrained(n, x))
        return cls(s_nodes=jnp.asarray(s), w_rated=float(w_rated), w2_paper=float(w2_paper),
                   bounds=bounds, **z)

    @classmethod
    def from_values(cls, s_nodes, w_rated, w2_paper, values: dict,
                    bounds: Bounds | None = None) -> GainSchedule:
        """Build from physical node values `{name: value or (n_nodes,)}` (zeta1, ratio,
        zeta2 (-), w2 (rad/s), nu2, nu3); missing ones take the paper's values."""
        s = np.asarray(s_nodes, dtype=float).reshape(-1)
        base = {k: np.asarray(v) for k, v in paper_values(s, float(w2_paper)).items()}
        factors = {n: (np.asarray(v, dtype=float) / base[n] if n in _FACTORS else v)
                   for n, v in values.items() if n in TUNABLE}
        unknown = [n for n in values if n not in TUNABLE]
        if unknown:
            raise ValueError(f"unknown quantities {unknown}; choose from {TUNABLE}.")
        return cls.from_factors(s, w_rated, w2_paper, factors, bounds)

    # --- physical values -------------------------------------------------------------

    def node_factors(self) -> dict:
        """Corrections at the nodes: `{name: (n_nodes,) array}` (factors, or `nu`)."""
        return {n: self.bounds.to_physical(n, getattr(self, f"z_{n}")) for n in TUNABLE}

    def factors(self, s) -> dict:
        """Corrections at speed(s) `s` = |w0|/w_rated (p.u.), interpolated."""
        s = jnp.abs(jnp.asarray(s))
        out = {}
        for n, v in self.node_factors().items():
            if n in _FACTORS:
                out[n] = jnp.exp(jnp.interp(s, self.s_nodes, jnp.log(v)))
            else:
                out[n] = jnp.interp(s, self.s_nodes, v)
        return out

    def values(self, s) -> dict:
        """Physical design at speed(s) `s` = |w0|/w_rated (p.u.): `{name: array}` with
        zeta1, ratio = w1/|w0|, zeta2 (-), w2 (rad/s), nu2, nu3 (-)."""
        base = paper_values(s, self.w2_paper)
        f = self.factors(s)
        return {n: (base[n] * f[n] if n in _FACTORS else f[n]) for n in TUNABLE}

    def __call__(self, motor, w0, i_dq):
        v = self.values(w0 / self.w_rated)
        pa = psi_a(motor, i_dq)
        pn = jnp.sqrt(jnp.sum(pa ** 2))
        n2 = v["nu2"] * 2.0 * v["zeta2"] * v["w2"] / pn
        n3 = v["nu3"] * v["w2"] ** 2 / pn
        return eso_gains(pa, w0, v["zeta1"], v["ratio"] * jnp.abs(w0), v["zeta2"], v["w2"],
                         n2=n2, n3=n3)

    def pi(self, motor, w0, i_dq):
        v = self.values(w0 / self.w_rated)
        return gains_pi(psi_a(motor, i_dq), v["zeta2"], v["w2"])


def filter_spec(schedule: GainSchedule, tuned=TUNABLE):
    """PyTree of booleans selecting the unconstrained leaves of `tuned` quantities.

    `eqx.partition(schedule, filter_spec(schedule, ("w2", "zeta2")))` returns the tuned
    part (a PyTree with only those arrays, `None` elsewhere) and the rest; the nodes, the
    rated speed and the bounds are never tuned.
    """
    tuned = tuple(tuned)
    unknown = [n for n in tuned if n not in TUNABLE]
    if unknown or not tuned:
        raise ValueError(
            f"tuned quantities must be a non-empty subset of {', '.join(TUNABLE)}; got "
            f"{', '.join(map(repr, tuned)) or 'nothing'}."
        )
    spec = jtu.tree_map(lambda _: False, schedule)
    return eqx.tree_at(lambda s: tuple(getattr(s, f"z_{n}") for n in tuned), spec,
                       replace=(True,) * len(tuned))


def zhang38_schedule(w_rated, s_nodes, *, w2=2 * math.pi * 50.0,
                     bounds: Bounds | None = None) -> GainSchedule:
    """The paper's design, (38) for the flux gains and (25) with bandwidth `w2` (rad/s)
    and `zeta2 = 1`, as a `GainSchedule` with nodes `s_nodes` (p.u.): the same gains as
    `ESODesign.zhang38(w_rated, w2)` at every speed (to rounding)."""
    return GainSchedule.paper(w_rated, s_nodes, w2, bounds)


def schedule_table(schedule: GainSchedule, s=None) -> dict:
    """Physical values as plain lists (for JSON): `{"s_pu": [...], name: [...]}` at `s`
    (p.u.; default the nodes), plus `w1_rad_s` (rad/s) and the corrections
    `factor_<name>` on the paper's design."""
    s = np.asarray(schedule.s_nodes if s is None else s, dtype=float).reshape(-1)
    v = {n: np.asarray(x, dtype=float) for n, x in schedule.values(jnp.asarray(s)).items()}
    f = {n: np.asarray(x, dtype=float) for n, x in schedule.factors(jnp.asarray(s)).items()}
    out = {"s_pu": s.tolist()}
    out.update({n: v[n].tolist() for n in TUNABLE})
    out["w1_rad_s"] = (v["ratio"] * s * float(schedule.w_rated)).tolist()
    out.update({f"factor_{n}": f[n].tolist() for n in _FACTORS})
    return out
