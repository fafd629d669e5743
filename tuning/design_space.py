r"""The design space in physical terms: bandwidths and damping, bounds from the drive.

A design is a point $x$ of physical coordinates (a tracking bandwidth in rad/s, a
damping ratio, an estimator bandwidth, a filter time constant, ...); the search moves an
unconstrained vector $z$ and sees $x_i = \exp(\ln l_i + (\ln h_i - \ln l_i)\,
\sigma(z_i))$ (log space, so that a step is a ratio; $\sigma$ the logistic function), so
every design it proposes is inside the bounds. `DesignSpace.observer(x, motor)` builds the
observer through the contract (`from_drive` + `with_design`).

**Bounds, derived from the drive** (`problem` fields in brackets):

- *tracking bandwidth* (the loop that turns the back-EMF / flux angle into angle and
  speed: zhang2022's $\omega_2$ (25), li's PLL $\omega_{pll}$, stumper's tracking filter
  $\sqrt{v_1}$): a type-2 loop lags a speed ramp $a$ by $a/\omega^2$ (rad), so the lowest
  bandwidth is $\sqrt{a_{max}/\theta_{lag}}$ with $a_{max} = n_p\tau_{max}/J$ (what the
  torque limit gives the unloaded rotor) and $\theta_{lag}$ = `ramp_lag_deg`; the
  highest is `w_T_s_max / T_s` (the discrete loop stays within a few per cent of the
  continuous one designed);
- *damping* (zhang2022's $\zeta_2$, the PLL's $\zeta_{pll}$, the tracking filter's
  $v_2 / (2\sqrt{v_1})$): `damping_range`;
- *estimator bandwidth* (li's LESO $\omega_0$ (16)): from the lowest tracking bandwidth
  (an estimator slower than the loop it feeds adds its lag to the loop's) to $1/T_s$
  (the LESOs are discretised exactly, so this is a noise bound, not a stability one);
- *explicit feedback rate* (morawiec2023's current-error rate and position correction,
  applied once per sampling period): from the lowest tracking bandwidth to
  `w_T_s_max / T_s`, the tracking bandwidth's discrete limit (at a rate of 1 / T_s the
  discrete observer is unstable);
- *filter time constant* (stumper's $T_{LP}$): from $T_s$ (the forward-Euler filter's
  stability limit) to $1/\omega_{min}$ of the tracking loop (a slower filter than that
  lags more than the allowed ramp lag);
- *fixed* (zhang2022's factors on the damping $\zeta_1$ and the decay rate
  $\zeta_1\omega_1$ of its schedule (38), `zeta1_scale` and `decay_scale`; the AFO's
  damping and ratio $\omega_1/|\omega_0|$ of a fixed-ratio schedule): bounds the
  observer class states itself (`tunable_bounds`), as physical constants of its design,
  not derived from the drive;
- any other tunable gain (li's FA-LESO $k_1$, $k_2$, morawiec2023's $k_c$): no physical
  rule here; its bounds are the observer contract's factor box around the paper's value
  (`tunable`), and the report says so.

An observer may name its own coordinates for some of its parameters
(`tuning_coordinates`, e.g. stumper's tracking filter as bandwidth $\sqrt{v_1}$ and damping
$v_2/(2\sqrt{v_1})$ instead of $v_1, v_2$); the search moves those, and the class maps
them to its design on the drive (`design_from_tuning`). morawiec2023's rotor-flux
observer is searched in the coordinates a reduction of its spectrum gives
(`pmsmjax.observers._rotor_flux_design`): the speed law's bandwidth at speed
$\omega_\gamma = \sqrt\gamma\,\psi_f/L_q$ (tracking), the d-axis current-error rate
$a_i = (1 + c_\alpha)R_s/L_d$ and the position correction's rate $c_\theta$ (explicit
feedback rates).

The paper's design is the starting point. Where it lies outside the derived bounds (stumper's
tracking filter and li's PLL are slower than the ramp-lag rule asks at their drives'
largest acceleration), the bounds are widened to hold it with a factor `PAPER_MARGIN` of
room, and `why` says so: a search that cannot return the baseline cannot promise no
regression.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from pmsmjax.observers import make_observer, observer_class

from .problem import TuningProblem
from .scenarios import max_acceleration


@dataclasses.dataclass(frozen=True)
class Coordinate:
    """One physical coordinate: `name`, `unit`, bounds `lo` < `hi`, `kind` (tracking,
    damping, estimator, time, contract), `why` (how the bounds were derived), `paper`
    (the paper design's value)."""

    name: str
    unit: str
    lo: float
    hi: float
    kind: str
    why: str
    paper: float


#: Where the paper's design lies outside the derived bounds, they are widened to hold it
#: with this factor of room (the search must be able to return the baseline).
PAPER_MARGIN = 1.25
#: Where `_stable_bounds` checks the linearised error dynamics (an observer class with
#: `tuning_spectral`): electrical speeds (p.u. of rated, both directions; below about
#: 0.13 p.u. morawiec2023's observer has no stable design at light load) and q-currents
#: (p.u. of the base current, d-current on MTPA), and how many values per coordinate.
SPECTRUM_SPEEDS_PU = (-1.0, -0.5, -0.2, 0.2, 0.5, 1.0)
SPECTRUM_IQ_PU = (-0.5, 0.0, 0.5, 1.0)
SPECTRUM_SCAN = 65
#: The kinds of coordinate whose bounds derive from the drive (the observer class's
#: `tunable_kinds`); any other tunable name is a "contract" coordinate.
KINDS = ("tracking", "damping", "estimator", "explicit", "time")


def _kind(cls, name: str) -> str:
    kind = cls.tunable_kinds.get(name, "contract")
    if kind not in (*KINDS, "contract"):
        raise ValueError(f"`{cls.__name__}.tunable_kinds[{name!r}]` is {kind!r}; choose "
                         f"one of {', '.join(KINDS)}.")
    return kind


def coordinate_names(observer: str) -> tuple[str, ...]:
    """The names of the design coordinates `DesignSpace` gives observer `observer`, in
    its order (`TuningProblem.tune` chooses among them)."""
    cls = observer_class(observer)
    return (*cls.tuning_coordinates, *cls.tunable_bounds,
            *(k for k in cls.tunable if k not in cls.tuning_replaces))


class DesignSpace:
    """The physical design space of `problem.observer` on `problem.drive()` (see the
    module docstring). Immutable after construction."""

    def __init__(self, problem: TuningProblem):
        self.observer_name = problem.observer
        self._drive = problem.drive()
        cls = observer_class(problem.observer)
        paper = make_observer(problem.observer, self._drive).design_parameters()
        self.paper_design = {k: float(v) for k, v in paper.items()
                             if v is not None and np.ndim(v) == 0}
        foc = problem.controller()
        a_max = max_acceleration(self._drive, foc)
        lag = math.radians(problem.ramp_lag_deg)
        w_lo = math.sqrt(a_max / lag)
        w_hi = problem.w_T_s_max / problem.T_s
        if w_lo >= w_hi:
            raise ValueError(
                f"`TuningProblem`: the tracking bandwidth needed for a ramp lag of "
                f"{problem.ramp_lag_deg:g} deg at a_max = {a_max:.4g} rad/s^2 "
                f"({w_lo:.4g} rad/s) exceeds the discrete limit w_T_s_max / T_s = "
                f"{w_hi:.4g} rad/s; allow more lag (ramp_lag_deg) or sample faster (T_s)")
        self.a_max = a_max
        self.w_track = (w_lo, w_hi)
        self._cls = cls
        coords = []
        tunable = {k: v for k, v in cls.tunable.items() if k not in cls.tuning_replaces}
        # the class's own coordinates for some of its parameters (a reparametrisation)
        paper_coords = cls.tuning_from_design(
            {k: self.paper_design[k] for k in cls.tuning_replaces}, self._drive)
        for name, (unit, kind) in cls.tuning_coordinates.items():
            if kind not in KINDS:
                raise ValueError(f"`{cls.__name__}.tuning_coordinates[{name!r}]` has kind "
                                 f"{kind!r}; choose one of {', '.join(KINDS)}.")
            coords.append(self._coord(name, unit, kind, float(paper_coords[name]), problem))
        # parameters whose bounds the class fixes (no rule from the drive)
        for name, (lo, hi, start, why) in cls.tunable_bounds.items():
            unit = cls.design_units[name].split(",")[0]
            coords.append(Coordinate(name, unit, lo, hi, "fixed", why, start))
        for name, box in tunable.items():
            unit = cls.design_units[name].split(",")[0]
            coords.append(self._coord(name, unit, _kind(cls, name), self.paper_design[name],
                                      problem, box))
        self.coordinates = tuple(coords)
        if cls.tuning_spectral:
            self.coordinates = self._stable_bounds()
        if problem.tune is not None:  # the others keep the paper's design
            self.coordinates = tuple(c for c in self.coordinates if c.name in problem.tune)

    def _coord(self, name, unit, kind, paper, problem, box=None) -> Coordinate:
        w_lo, w_hi = self.w_track
        if kind == "tracking":
            lo, hi = w_lo, w_hi
            why = (f"ramp lag <= {problem.ramp_lag_deg:g} deg at a_max = "
                   f"{self.a_max:.4g} rad/s^2 (sqrt(a_max / lag)); w T_s <= "
                   f"{problem.w_T_s_max:g}")
        elif kind == "damping":
            lo, hi = problem.damping_range
            why = "damping_range"
        elif kind == "estimator":
            lo, hi = w_lo, 1.0 / problem.T_s
            why = "at least the lowest tracking bandwidth; at most 1/T_s (noise)"
        elif kind == "explicit":
            lo, hi = w_lo, w_hi
            why = ("at least the lowest tracking bandwidth; applied once per sampling "
                   f"period: w T_s <= {problem.w_T_s_max:g}")
        elif kind == "time":
            lo, hi = problem.T_s, 1.0 / w_lo
            why = "T_s (forward-Euler stability) to 1/(lowest tracking bandwidth)"
        else:
            lo, hi = paper * box[0], paper * box[1]
            why = (f"no physical rule: the observer contract's box {box[0]:g}..{box[1]:g}"
                   f" x the paper's value")
        if not lo <= paper <= hi:  # the baseline must stay reachable: no regression
            lo, hi = min(lo, paper / PAPER_MARGIN), max(hi, paper * PAPER_MARGIN)
            why += (f"; widened to hold the paper's value {paper:.4g} {unit} (x/"
                    f"{PAPER_MARGIN:g} of it), which lies outside the derived bounds")
        return Coordinate(name, unit, float(lo), float(hi), kind, why, float(paper))

    def _stable_bounds(self) -> tuple[Coordinate, ...]:
        """Each coordinate's bounds narrowed to the interval around the paper's design
        (the others held at it) in which `analysis.linearization` (averaged over the
        rotor angle) is stable at every point of `SPECTRUM_SPEEDS_PU` x
        `SPECTRUM_IQ_PU` (MTPA d-current), scanned at `SPECTRUM_SCAN` log-spaced values
        between the rule's bounds; the bounds are the last stable values (module
        docstring). Concrete even where the space is built while a caller traces (the
        comparison job builds it inside its jitted runs)."""
        coords = self.coordinates
        grids = [np.unique(np.r_[np.geomspace(c.lo, c.hi, SPECTRUM_SCAN), c.paper])
                 for c in coords]
        with jax.ensure_compile_time_eval():
            stable = self._scan_stable(grids)
        where = (f"speeds +-{'/'.join(f'{v:g}' for v in SPECTRUM_SPEEDS_PU if v > 0)} "
                 f"p.u. x i_q {min(SPECTRUM_IQ_PU):g}..{max(SPECTRUM_IQ_PU):g} p.u. (MTPA)")
        out = []
        for j, (c, g) in enumerate(zip(coords, grids)):
            ok, k = stable[j, :len(g)], int(np.searchsorted(g, c.paper))
            if not ok[k]:
                out.append(dataclasses.replace(
                    c, why=c.why + f"; the paper's design is not stable at every point "
                                   f"of {where}: bounds kept"))
                continue
            lo, hi = k, k
            while lo > 0 and ok[lo - 1]:
                lo -= 1
            while hi < len(g) - 1 and ok[hi + 1]:
                hi += 1
            out.append(dataclasses.replace(
                c, lo=float(g[lo]), hi=float(g[hi]),
                why=c.why + "; narrowed to where the linearised error dynamics "
                            "(analysis.linearization, averaged over the angle) are stable at "
                            f"{where}, the others at the paper's values"))
        return tuple(out)

    def _scan_stable(self, grids) -> np.ndarray:
        """`(n_coords, n)` bool: stable at each value of each coordinate's scan `grids`
        (padded to one length with their last value), the others at the paper's."""
        from pmsmjax import analysis, mtpa_i_d

        drive, coords = self._drive, self.coordinates
        m = drive.three_phase_motor
        w, i_q = np.meshgrid(np.array(SPECTRUM_SPEEDS_PU) * drive.w_rated,
                             np.array(SPECTRUM_IQ_PU) * drive.base.I_b)
        w, i_q = jnp.asarray(w.ravel()), jnp.asarray(i_q.ravel())
        i_dq = jnp.stack([mtpa_i_d(i_q, m), i_q], -1)

        def worst(x):  # the largest real part over the operating points (1/s)
            obs = self.observer(x)
            A = jax.vmap(lambda w_, i_: analysis.linearization(obs, m, w_, i_))(w, i_dq)
            return jnp.max(jnp.real(jnp.linalg.eigvals(A)))

        x0 = np.array([c.paper for c in coords])
        n = max(len(g) for g in grids)
        X = np.repeat(x0[None], len(coords) * n, 0)
        for j, g in enumerate(grids):
            X[j * n:(j + 1) * n, j] = np.pad(g, (0, n - len(g)), mode="edge")
        return np.asarray(jax.jit(jax.vmap(worst))(jnp.asarray(X))).reshape(
            len(coords), n) < 0

    # --- coordinates ------------------------------------------------------------------
    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.coordinates)

    @property
    def n(self) -> int:
        return len(self.coordinates)

    def _logs(self):
        lo = jnp.asarray([math.log(c.lo) for c in self.coordinates])
        hi = jnp.asarray([math.log(c.hi) for c in self.coordinates])
        return lo, hi

    def to_physical(self, z) -> jnp.ndarray:
        """Unconstrained `z` (n,) -> physical coordinates (n,), inside the bounds."""
        lo, hi = self._logs()
        return jnp.exp(lo + (hi - lo) * jax.nn.sigmoid(z))

    def to_unconstrained(self, x) -> jnp.ndarray:
        """Physical coordinates (n,) -> `z`; values outside the bounds are projected to
        just inside them."""
        lo, hi = self._logs()
        u = (jnp.log(jnp.asarray(x, dtype=float)) - lo) / (hi - lo)
        u = jnp.clip(u, 1e-3, 1 - 1e-3)
        return jnp.log(u) - jnp.log1p(-u)

    def paper_point(self) -> np.ndarray:
        """The paper design's physical coordinates (possibly outside the bounds)."""
        return np.array([c.paper for c in self.coordinates])

    def paper_inside(self) -> bool:
        return all(c.lo <= c.paper <= c.hi for c in self.coordinates)

    def as_dict(self, x) -> dict:
        """`{name: float}` of physical coordinates `x`."""
        return {c.name: float(v) for c, v in zip(self.coordinates, np.asarray(x))}

    def design(self, x) -> dict:
        """The observer's design parameters (`design_units` names) of coordinates `x`
        (may be traced)."""
        x = jnp.asarray(x)
        return self._cls.design_from_tuning(
            {c.name: x[i] for i, c in enumerate(self.coordinates)}, self._drive)

    def observer(self, x, motor=None):
        """The observer with the design `x` (physical coordinates; may be traced; None:
        the paper's design as published, e.g. zhang2022's speed schedule (38)) and the
        machine model `motor` (default the drive's)."""
        obs = make_observer(self.observer_name, self._drive, motor=motor)
        return obs if x is None else obs.with_design(**self.design(x))

    def bounds_table(self) -> list[dict]:
        """The coordinates, their bounds and how they were derived (for the report)."""
        return [dataclasses.asdict(c) | {"paper_inside": c.lo <= c.paper <= c.hi}
                for c in self.coordinates]


__all__ = ["Coordinate", "DesignSpace"]
