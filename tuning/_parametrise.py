r"""Tunable observer designs: unconstrained variables <-> physical design parameters.

Every design the tuner moves is an `AbstractDesign`: an equinox Module whose tunable
leaves are unconstrained reals, which maps them to a physical design inside a box and
applies it to an observer built by the registry (`pmsmjax.observers.make_observer`).
Which implementation a tuning run uses follows from the observer class's declaration
(`tuning.scenarios.parametrisation_of`), never from its name:

- `GainSchedule`, the speed-scheduled zhang2022 gains below, for observers that declare
  `speed_scheduled` design parameters (a gain schedule in their `design` field: the ESO,
  LESO and AFO);
- `ConstantDesign`, constant factors on the paper's design (`from_drive`) for the design
  parameters an observer declares in `tunable`, applied with `observer.with_design`, for
  any other observer (or for those, on request).

**The speed-scheduled zhang2022 gains.** The observer gains of zhang2022 follow from six
design quantities at each operating speed $\omega_0$ (Sec. III;
`pmsmjax.observers.eso_gains`):

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

**Constant factors** (`ConstantDesign`): for each declared design parameter $p$ with
paper value $p_0$ (`from_drive(drive).design_parameters()`) and factor box
$(c_{lo}, c_{hi})$ (the class's `tunable`, or `FactorBounds`),
$p = p_0\,c_{lo}\,(c_{hi}/c_{lo})^{\sigma(z)}$, the same log-sigmoid map (factor 1, the
paper's design, at $\sigma(z) = \log(1/c_{lo})/\log(c_{hi}/c_{lo})$).

**Which leaves are tuned** is chosen by filtering the PyTree, not by lists of arrays:
`filter_spec(design, names)` builds a PyTree of booleans with `eqx.tree_at`, and
`eqx.partition(design, spec)` / `eqx.combine` split and rebuild it.
"""

from __future__ import annotations

import abc
import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from pmsmjax import jmul
from pmsmjax.observers import AbstractGainSchedule, eso_gains, gains_pi, psi_a


#: Design quantities of `GainSchedule`, in the order they are reported.
TUNABLE = ("zeta1", "ratio", "zeta2", "w2", "nu2", "nu3")

#: Quantities written as positive factors on the paper's design; the others are signed.
_FACTORS = ("zeta1", "ratio", "zeta2", "w2")

_UNITS = {"zeta1": "-", "ratio": "-", "zeta2": "-", "w2": "rad/s", "nu2": "-", "nu3": "-"}


class AbstractDesign(eqx.Module):
    """A tunable observer design (see the module docstring).

    Subclasses implement `quantities` (the names of the tunable quantities, in report
    order), `leaf(name)` (the unconstrained array of a quantity), `apply(observer)` (the
    observer with this design) and `table(s)` (the physical design as plain lists, for
    reports), and set the class attributes below.
    """

    #: How the baseline is labelled in reports and plots.
    label: ClassVar[str] = "paper design"
    #: Which parametrisation this is ("scheduled" or "constant").
    kind: ClassVar[str] = ""
    #: An ablation the job runs as well: `(name, frozen quantities, description)`, the
    #: same tuning with those quantities held at the paper's values; None: none.
    ablation: ClassVar[tuple[str, tuple[str, ...], str] | None] = None

    @abc.abstractmethod
    def quantities(self) -> tuple[str, ...]:
        """Names of every tunable quantity of this design."""

    @abc.abstractmethod
    def leaf(self, name: str):
        """The unconstrained array of quantity `name` (what `filter_spec` selects)."""

    @abc.abstractmethod
    def apply(self, observer):
        """`observer` (built by the registry) with this design."""

    @abc.abstractmethod
    def table(self, s=None) -> dict:
        """The physical design as plain lists/floats (JSON), e.g. for summary.json."""

    def describe(self) -> str:
        """One line describing the paper's design this parametrisation starts from."""
        return "the paper's design (the tuner's starting point)"

    def pole_bounds(self, w0):
        """Smooth upper bounds of the designed fastest poles at electrical speed `w0`
        (rad/s) for the sampling penalty, or None: the penalty then estimates the
        fastest pole from the linearisation at the designed equilibrium."""
        del w0
        return None

    def design_margins(self, observer, op):
        """Normalised margins (> 0 wanted, O(1)) that this parametrisation keeps on top of
        the generic penalty, at operating point `op` for `observer` (with its mismatched
        model), or None (the default: none). The penalty adds `sp(-m)` for each."""
        del observer, op
        return None


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


class GainSchedule(AbstractDesign, AbstractGainSchedule):
    r"""Smooth, tunable ESO gain schedule over speed (see the module docstring).

    Use it as the `design` of `ESOObserver`, `LESOObserver` or `AFOObserver` (`apply`
    puts it into the `design` field of any observer that declares `speed_scheduled`
    design parameters and holds an `AbstractGainSchedule` there). The gains at
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

    label: ClassVar[str] = "(38)/(25)"
    kind: ClassVar[str] = "scheduled"
    ablation: ClassVar[tuple[str, tuple[str, ...], str] | None] = (
        "min_norm_25", ("nu2", "nu3"),
        "the same tuning restricted to the minimum-norm speed gains (25) (nu2 = nu3 = 0 "
        "frozen by the filter spec)")

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

    # --- AbstractDesign ---------------------------------------------------------------

    def quantities(self) -> tuple[str, ...]:
        return TUNABLE

    def leaf(self, name: str):
        return getattr(self, f"z_{name}")

    def apply(self, observer):
        return set_schedule(observer, self)

    def table(self, s=None) -> dict:
        return schedule_table(self, s)

    def describe(self) -> str:
        return ("paper: flux gains (38), minimum-norm speed gains (25), w2 = 2 pi "
                "w2_paper_hz, zeta2 = 1 (the tuner's starting point)")

    def design_margins(self, observer, op):
        r"""$\kappa/0.05 - 1$ with zhang2022's reduction slope bound $\kappa$
        (`reduction_kappa`) of the observer's gains (15) at `op`: the family's own
        equilibrium route (`fast_equilibria`, the reduction behind
        `pmsmjax.analysis.eso_equilibria`) needs $\kappa > 0$ and reports a degenerate
        point otherwise. The minimum-norm gains (25) have $\kappa = \omega_1^2/\omega_0^2$;
        null-space components can make it negative, so the tuner is kept where
        feasibility can be certified."""
        w0 = op.w_m
        return (reduction_kappa(observer.linear_gains(w0, op.i_dq), w0) / KAPPA_MIN
                - 1.0)[None]

    def pole_bounds(self, w0):
        r"""With $p(\zeta, \omega) = \omega(\zeta + \sqrt{\zeta^2 + 1})$ (a smooth upper
        bound of the faster pole of $s^2 + 2\zeta\omega s + \omega^2$): the flux and the
        speed/angle poles at `w0` (rad/s), `(2,)` (1/s)."""
        v = self.values(w0 / self.w_rated)
        p = lambda z, w: w * (z + jnp.sqrt(z * z + 1.0))  # noqa: E731
        return jnp.stack([p(v["zeta1"], v["ratio"] * jnp.abs(w0)), p(v["zeta2"], v["w2"])])


#: Smallest slope bound kept by `GainSchedule.design_margins`.
KAPPA_MIN = 0.05


def reduction_kappa(gains, w0):
    r"""$\kappa = 1 - u\cdot JG_1u/\omega_0$, $u = Jg_3^T/\|g_3\|$ of zhang2022's gains
    (15) `gains` (`ESOGains`) at electrical speed `w0` (rad/s): the slope bound of the
    reduction `pmsmjax.analysis.eso_equilibria` relies on (it needs $\kappa > 0$, else it
    reports status -1). With the minimum-norm gains (25) $\kappa = \omega_1^2/\omega_0^2
    > 0$; null-space components rotate $u$ and can make it negative when $\zeta_1 > 1$."""
    g3 = gains.g3
    u = jmul(g3) / jnp.sqrt(jnp.sum(g3 ** 2) + 1e-300)
    return 1.0 - jnp.dot(u, jmul(gains.G1 @ u)) / w0


def set_schedule(observer, schedule: AbstractGainSchedule):
    """`observer` with the gain schedule `schedule` in its `design` field: for observers
    that declare `speed_scheduled` design parameters (zhang2022's ESO, LESO, AFO)."""
    cls = type(observer)
    if not cls.speed_scheduled or not isinstance(getattr(observer, "design", None),
                                                 AbstractGainSchedule):
        raise ValueError(
            f"{cls.__name__} takes no speed-scheduled gains (it declares no "
            f"`speed_scheduled` design parameters, or has no gain schedule in its "
            f"`design` field); tune it with the constant parametrisation.")
    return eqx.tree_at(lambda o: o.design, observer, schedule)


def filter_spec(design: AbstractDesign, tuned=None):
    """PyTree of booleans selecting the unconstrained leaves of `tuned` quantities
    (default: all of `design.quantities()`).

    `eqx.partition(schedule, filter_spec(schedule, ("w2", "zeta2")))` returns the tuned
    part (a PyTree with only those arrays, `None` elsewhere) and the rest; the nodes, the
    rated speed, the paper's values and the bounds are never tuned.
    """
    if not isinstance(design, AbstractDesign):
        raise ValueError(f"`filter_spec(design=...)` must be a `tuning.AbstractDesign` "
                         f"(`GainSchedule`, `ConstantDesign`); got {type(design).__name__}.")
    names = design.quantities()
    tuned = names if tuned is None else tuple(tuned)
    unknown = [n for n in tuned if n not in names]
    if unknown or not tuned:
        raise ValueError(
            f"tuned quantities must be a non-empty subset of {', '.join(names)}; got "
            f"{', '.join(map(repr, tuned)) or 'nothing'}."
        )
    spec = jtu.tree_map(lambda _: False, design)
    return eqx.tree_at(lambda d: tuple(d.leaf(n) for n in tuned), spec,
                       replace=(True,) * len(tuned))


# ---------------------------------------------------------------------------------------
# Constant factors on the paper's design, for any observer that declares `tunable`
# ---------------------------------------------------------------------------------------

def _check_factor_box(owner: str, name: str, b) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in b)
    except (TypeError, ValueError):
        raise ValueError(f"`{owner}`: the bounds of {name!r} must be a pair (lo, hi) of "
                         f"numbers; got {b!r}.") from None
    if not (math.isfinite(lo) and math.isfinite(hi)) or not 0 < lo < 1 < hi:
        raise ValueError(
            f"`{owner}`: the bounds of {name!r} are factors on the paper's value and must "
            f"satisfy 0 < lo < 1 < hi (positive; containing 1, the paper's design); got "
            f"({lo!r}, {hi!r}).")
    return lo, hi


class FactorBounds(eqx.Module):
    """Open boxes of constant design parameters, as factors `(lo, hi)` on the paper's
    values (`0 < lo < 1 < hi`): `FactorBounds.of(names, boxes)`; `box(name)`,
    `as_dict()`. Hashable (static tuples), so a `TuningConfig` can hold it."""

    names: tuple[str, ...] = eqx.field(static=True)
    lo: tuple[float, ...] = eqx.field(static=True)
    hi: tuple[float, ...] = eqx.field(static=True)

    @classmethod
    def of(cls, boxes: dict, owner: str = "FactorBounds") -> FactorBounds:
        """From `{name: (lo, hi)}` (validated)."""
        names, lo, hi = [], [], []
        for name, b in boxes.items():
            a, c = _check_factor_box(owner, name, b)
            names.append(str(name))
            lo.append(a)
            hi.append(c)
        return cls(names=tuple(names), lo=tuple(lo), hi=tuple(hi))

    def box(self, name: str) -> tuple[float, float]:
        if name not in self.names:
            raise ValueError(f"no bounds for {name!r}; FactorBounds has "
                             f"{', '.join(self.names)}.")
        k = self.names.index(name)
        return self.lo[k], self.hi[k]

    def as_dict(self) -> dict:
        return {n: (a, b) for n, a, b in zip(self.names, self.lo, self.hi)}


class ConstantDesign(AbstractDesign):
    r"""Constant design parameters as factors on the paper's design, for any observer.

    For each name $p$: $p = p_0 c$, $c = c_{lo}(c_{hi}/c_{lo})^{\sigma(z_p)}$ with the
    paper's value $p_0$ (`from_drive(drive).design_parameters()[p]`, > 0) and the box
    $(c_{lo}, c_{hi})$ of `bounds`; `apply(observer)` is
    `observer.with_design(**values())` (traced values: works under `vmap` and `grad`).

    Build it with `ConstantDesign.paper(observer, names, bounds)` (all factors 1).

    **Fields:** `names` (static), `paper_values` `(n,)` (SI, as `design_units`), `z`
    (`{name: scalar}`, unconstrained), `bounds` (`FactorBounds`), `units` (static).
    """

    names: tuple[str, ...] = eqx.field(static=True)
    paper_values: jnp.ndarray
    z: dict
    bounds: FactorBounds
    units: tuple[str, ...] = eqx.field(static=True)

    kind: ClassVar[str] = "constant"

    @classmethod
    def paper(cls, observer, names=None, bounds: FactorBounds | None = None
              ) -> ConstantDesign:
        """The design of `observer` (its `from_drive` design) for the declared `names`
        (default: all of the class's `tunable`), all factors 1; `bounds` default: the
        class's declaration."""
        ocls = type(observer)
        declared = dict(ocls.tunable)
        names = tuple(declared) if names is None else tuple(names)
        if not names:
            raise ValueError(f"{ocls.__name__} declares no tunable design (its `tunable` "
                             f"is empty).")
        bounds = FactorBounds.of({n: declared[n] for n in names if n in declared},
                                 f"{ocls.__name__}.tunable") if bounds is None else bounds
        have = observer.design_parameters()
        vals = []
        for n in names:
            if n not in have:
                raise ValueError(
                    f"{ocls.__name__} declares {n!r} tunable, but its design has no such "
                    f"parameter (design_parameters: {', '.join(have) or 'none'}).")
            v = np.asarray(have[n], dtype=float)
            if v.shape != () or not (math.isfinite(float(v)) and float(v) > 0):
                raise ValueError(
                    f"{ocls.__name__}: the paper's value of the tunable {n!r} is {v!r}; a "
                    f"factor parametrisation needs a finite scalar > 0.")
            vals.append(float(v))
            bounds.box(n)  # every name must have bounds
        z = {}
        for n in names:
            lo, hi = bounds.box(n)
            u = math.log(1.0 / lo) / math.log(hi / lo)
            z[n] = jnp.asarray(np.float64(math.log(u) - math.log1p(-u)))
        units = tuple(str(ocls.design_units.get(n, "")) for n in names)
        return cls(names=names, paper_values=jnp.asarray(vals), z=z, bounds=bounds,
                   units=units)

    def with_factors(self, factors: dict) -> ConstantDesign:
        """A copy with the given factors `{name: factor}` (strictly inside the box)."""
        z = dict(self.z)
        for n, f in factors.items():
            if n not in self.names:
                raise ValueError(f"unknown quantity {n!r}; choose from "
                                 f"{', '.join(self.names)}.")
            lo, hi = self.bounds.box(n)
            f = float(f)
            if not lo < f < hi:
                raise ValueError(f"the factor {f!r} of {n!r} lies outside the open box "
                                 f"({lo:g}, {hi:g}); widen the bounds.")
            u = math.log(f / lo) / math.log(hi / lo)
            z[n] = jnp.asarray(np.float64(math.log(u) - math.log1p(-u)))
        return eqx.tree_at(lambda d: d.z, self, z)

    def factors(self) -> dict:
        """`{name: factor}` on the paper's values (traced where `z` is)."""
        out = {}
        for n in self.names:
            lo, hi = self.bounds.box(n)
            out[n] = lo * jnp.exp(jax.nn.sigmoid(self.z[n]) * math.log(hi / lo))
        return out

    def values(self) -> dict:
        """`{name: value}`: the physical design (SI, as the observer's `design_units`)."""
        f = self.factors()
        return {n: self.paper_values[k] * f[n] for k, n in enumerate(self.names)}

    def quantities(self) -> tuple[str, ...]:
        return self.names

    def leaf(self, name: str):
        return self.z[name]

    def apply(self, observer):
        return observer.with_design(**self.values())

    def describe(self) -> str:
        return ("the paper's default design of the observer (`from_drive`): "
                + ", ".join(f"{n} = {float(v):.6g}" for n, v in
                            zip(self.names, np.asarray(self.paper_values))))

    def table(self, s=None) -> dict:
        del s
        v = {n: float(x) for n, x in self.values().items()}
        f = {n: float(x) for n, x in self.factors().items()}
        return dict(values=v, factors=f,
                    paper={n: float(x) for n, x in zip(self.names,
                                                       np.asarray(self.paper_values))},
                    bounds={n: list(self.bounds.box(n)) for n in self.names},
                    units=dict(zip(self.names, self.units)))


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
