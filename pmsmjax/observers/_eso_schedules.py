r"""The gain schedules of zhang2022's flux observers (`_eso`): the observer gains as a
function of the operating point. `ESODesign` places the poles at every operating point
(the paper's adaptive gains: the flux schedule zhang2022 (38), a fixed ratio or a fixed
$\omega_1$ with (17), and (25)); `FixedGains` freezes them at one point (zhang2022 Fig.
11's fixed gains). The formulas are `_eso_design`'s; a tuned table of gains
(`pmsmjax.TabulatedDesign`) is another `AbstractGainSchedule`.
"""

from __future__ import annotations

import abc
import math

import equinox as eqx
import jax.numpy as jnp

from .._plant._params import PMSMParams
from .._validate import check_positive
from ._eso_design import ESOGains, check_design, eso_gains, gains_pi, psi_a, zhang38


#: The design parameters each flux schedule needs (`ESODesign`, `with_design`).
SCHEDULE_PARAMS = {"zhang38": ("w_rated",), "fixed_ratio": ("zeta1", "ratio"),
                   "fixed_w1": ("zeta1", "w1", "w_min")}
#: The optional factors of the zhang38 schedule on (38)'s damping and decay rate.
ZHANG38_SCALES = ("zeta1_scale", "decay_scale")

#: The tuner's flux-loop coordinates (`tunable_bounds`: lo, hi, the paper design's value,
#: why): (38) scaled, and a fixed-ratio schedule (zeta1, w1/|w0|) whose values at half the
#: rated speed stand for (38).
SCALED_38_BOUNDS = {
    "zeta1_scale": (0.33, 3.0, 1.0, "factor on (38)'s flux damping: zeta1 from 0.5 (the "
                    "lightest damping of zhang2022 Fig. 1's designs) to 3 x (38)"),
    "decay_scale": (0.25, 3.0, 1.0, "factor on (38)'s flux decay rate 1.5 |w0|: the flux "
                    "error's envelope falls by exp(-0.375) to exp(-4.5) per radian")}
FIXED_RATIO_BOUNDS = {
    "zeta1": (0.5, 4.0, 2.0, "flux damping of zhang2022 (17); (38) spans 1.5..2.5"),
    "ratio": (0.2, 2.0, 0.75, "w1/|w0| of zhang2022 Fig. 1; (38) spans 1..0.6")}


def schedule_for(values: dict, current: str) -> str:
    """The flux schedule implied by the names being set: `w1` -> fixed_w1, `zeta1` or
    `ratio` -> fixed_ratio (unless the schedule already is fixed_w1), `w_rated` or a
    scale of (38) (`zeta1_scale`, `decay_scale`) -> zhang38, else unchanged."""
    if "w1" in values or "w_min" in values:
        return "fixed_w1"
    if "ratio" in values:
        return "fixed_ratio"
    if "zeta1" in values and current == "zhang38":
        return "fixed_ratio"
    if "w_rated" in values or any(k in values for k in ZHANG38_SCALES):
        return "zhang38"
    return current


class AbstractGainSchedule(eqx.Module):
    """Observer gains as a function of the operating point.

    Subclasses implement `__call__(motor, w0, i_dq) -> ESOGains` (the gains of (15) at
    electrical speed `w0` (rad/s) and current `i_dq` (A, estimator frame), for the
    observer's machine model `motor`) and `pi(motor, w0, i_dq) -> (k_p, k_i)`, the speed
    law (53) of the adaptive full-order observer.
    """

    @abc.abstractmethod
    def __call__(self, motor: PMSMParams, w0, i_dq) -> ESOGains:
        ...

    @abc.abstractmethod
    def pi(self, motor: PMSMParams, w0, i_dq):
        ...


class ESODesign(AbstractGainSchedule):
    r"""Gains from pole placement, recomputed at every operating point (adaptive gains).

    Flux poles $s^2 + 2\zeta_1\omega_1 s + \omega_1^2$ by (17); speed/angle poles
    $s^2 + 2\zeta_2\omega_2 s + \omega_2^2$ by (25) (minimum norm; `n2`, `n3` add the null
    space of (19) for comparison). $(\zeta_1, \omega_1)$ follow `schedule`:

    - `"zhang38"`: the suggestion (38), $\zeta_1 = 1.5 + |\omega_0|/\omega_r$,
      $\omega_1 = 1.5|\omega_0|/\zeta_1$ (needs `w_rated`); `zeta1_scale` $k_\zeta$ and
      `decay_scale` $k_\sigma$ keep its shape over speed and scale it:
      $\zeta_1 = k_\zeta(1.5 + |\omega_0|/\omega_r)$, $\zeta_1\omega_1 =
      1.5 k_\sigma|\omega_0|$ (both 1: (38)).
    - `"fixed_ratio"`: $\zeta_1$ = `zeta1`, $\omega_1$ = `ratio` $|\omega_0|$ (the axes of
      Fig. 1; Fig. 9's infeasible design is `zeta1=0.5, ratio=0.5`).
    - `"fixed_w1"`: constant `zeta1`, `w1`; $\omega_1^2/\omega_0$ in (17) is evaluated with
      $|\omega_0|$ clamped to `w_min` (> 0 required).

    In an observer the operating point is the observer's own $\hat\omega$ and the
    measured current in its estimator frame, so the gains adapt to the operating
    condition as the paper's "adaptive gains" (Fig. 11) do.

    $\omega_0 \to 0$: for `"zhang38"` and `"fixed_ratio"` $\omega_1 \propto |\omega_0|$, so
    the $\omega_1^2/\omega_0$ term of (17) tends to 0 and $G_1 \to 0$: at standstill the
    flux feedback switches off and the flux is integrated open loop (the PM flux
    direction is not observable from the back-EMF there), while $g_2$, $g_3$ keep their
    values. The flux error then decays at $\zeta_1\omega_1 = 1.5|\omega_0|$ (38), i.e.
    by a fixed factor per radian of rotation.

    **Arguments:**

    - `w2`: speed/angle natural frequency (rad/s), the "observer bandwidth" of the paper.
    - `zeta2`: its damping (-), default 1 (the AFO law (53) is critically damped).
    - `schedule`: see above.
    - `w_rated`: rated electrical speed (rad/s), for `"zhang38"`.
    - `zeta1_scale`, `decay_scale`: factors (-) on (38)'s damping and decay rate, for
      `"zhang38"`; default 1.
    - `zeta1`: flux damping (-), for `"fixed_ratio"` and `"fixed_w1"`.
    - `ratio`: $\omega_1/|\omega_0|$ (-), for `"fixed_ratio"`.
    - `w1`: flux natural frequency (rad/s), for `"fixed_w1"`.
    - `w_min`: clamp of $|\omega_0|$ in (17) for `"fixed_w1"` (rad/s).
    - `n2`, `n3`: null-space components of a non-minimum-norm solution of (19)
      (see `gains_g23`); 0 = (25).
    """

    w2: float
    zeta2: float
    schedule: str = eqx.field(static=True)
    w_rated: float | None
    zeta1: float | None
    ratio: float | None
    w1: float | None
    w_min: float
    n2: float
    n3: float
    zeta1_scale: float
    decay_scale: float

    def __init__(self, w2=2 * math.pi * 50.0, zeta2=1.0, schedule="zhang38", *,
                 w_rated=None, zeta1=None, ratio=None, w1=None, w_min=0.0, n2=0.0,
                 n3=0.0, zeta1_scale=1.0, decay_scale=1.0):
        if schedule not in SCHEDULE_PARAMS:
            raise ValueError(
                f"`ESODesign(schedule=...)` must be one of {', '.join(SCHEDULE_PARAMS)}; "
                f"got {schedule!r}."
            )
        need = SCHEDULE_PARAMS[schedule]
        given = dict(w_rated=w_rated, zeta1=zeta1, ratio=ratio, w1=w1, w_min=w_min)
        for name in need:
            if given[name] is None or (name == "w_min" and not _nonzero(w_min)):
                raise ValueError(
                    f"`ESODesign(schedule={schedule!r})` needs `{name}`"
                    + (" > 0 (rad/s): the w1^2/w0 term of (17) is singular at w0 = 0."
                       if name == "w_min" else ".")
                )
        self.w2, self.zeta2, self.schedule = w2, zeta2, schedule
        self.w_rated, self.zeta1, self.ratio, self.w1 = w_rated, zeta1, ratio, w1
        self.w_min, self.n2, self.n3 = w_min, n2, n3
        self.zeta1_scale, self.decay_scale = zeta1_scale, decay_scale

    def __check_init__(self):
        check_design("ESODesign", zeta1=self.zeta1, w1=self.w1, ratio=self.ratio,
                     zeta2=self.zeta2, w2=self.w2)
        check_positive("ESODesign", "w_rated", self.w_rated, "rad/s")
        check_positive("ESODesign", "w_min", self.w_min, "rad/s", allow_zero=True)
        check_positive("ESODesign", "zeta1_scale", self.zeta1_scale, "-")
        check_positive("ESODesign", "decay_scale", self.decay_scale, "-")

    @classmethod
    def zhang38(cls, w_rated, w2=2 * math.pi * 50.0, zeta2=1.0, **kw) -> ESODesign:
        """The paper's design: (38) for the flux gains, (25) for `w2`, `zeta2`."""
        return cls(w2, zeta2, "zhang38", w_rated=w_rated, **kw)

    @classmethod
    def fixed_ratio(cls, zeta1, ratio, w2=2 * math.pi * 50.0, zeta2=1.0, **kw
                    ) -> ESODesign:
        """`zeta1` constant, `w1 = ratio |w0|` (Fig. 1 / Fig. 9)."""
        return cls(w2, zeta2, "fixed_ratio", zeta1=zeta1, ratio=ratio, **kw)

    @classmethod
    def fixed_w1(cls, zeta1, w1, w_min, w2=2 * math.pi * 50.0, zeta2=1.0, **kw
                 ) -> ESODesign:
        """Constant `zeta1`, `w1` (rad/s); `|w0|` clamped to `w_min` (rad/s) in (17)."""
        return cls(w2, zeta2, "fixed_w1", zeta1=zeta1, w1=w1, w_min=w_min, **kw)

    def zeta1_w1(self, w0):
        """Flux design `(zeta1, w1)` at electrical speed `w0` (rad/s)."""
        if self.schedule == "zhang38":
            return zhang38(w0, self.w_rated, self.zeta1_scale, self.decay_scale)
        if self.schedule == "fixed_ratio":
            return self.zeta1 + 0.0 * w0, self.ratio * jnp.abs(w0)
        return self.zeta1 + 0.0 * w0, self.w1 + 0.0 * w0

    def __call__(self, motor: PMSMParams, w0, i_dq) -> ESOGains:
        zeta1, w1 = self.zeta1_w1(w0)
        w_min = self.w_min if self.schedule == "fixed_w1" else 0.0
        return eso_gains(psi_a(motor, i_dq), w0, zeta1, w1, self.zeta2, self.w2,
                         w_min=w_min, n2=self.n2, n3=self.n3)

    def pi(self, motor: PMSMParams, w0, i_dq):
        del w0
        return gains_pi(psi_a(motor, i_dq), self.zeta2, self.w2)


def _nonzero(x) -> bool:
    try:
        return bool(x)
    except Exception:  # a tracer: cannot check
        return True


class FixedGains(AbstractGainSchedule):
    """Gains frozen at one design point (the fixed-gain observer of Fig. 11).

    Use `FixedGains.at(design, motor, w0, i_dq)` to freeze a design at speed `w0`
    (rad/s) and current `i_dq` (A); the gains then stay the same at every operating
    point, as the paper's "fixed gains [17]" tuned at 0.2 p.u. do.

    **Arguments:**

    - `gains`: `ESOGains` (G1 in 1/s, g2, g3 per V s).
    - `k_p`, `k_i`: speed-law gains of (53) for `AFOObserver` (rad/s and rad/s^2 per V s).
    """

    gains: ESOGains
    k_p: float
    k_i: float

    @classmethod
    def at(cls, design: ESODesign, motor: PMSMParams, w0, i_dq=(0.0, 0.0)) -> FixedGains:
        i_dq = jnp.asarray(i_dq, dtype=float)
        k_p, k_i = design.pi(motor, w0, i_dq)
        return cls(gains=design(motor, w0, i_dq), k_p=k_p, k_i=k_i)

    def __call__(self, motor, w0, i_dq) -> ESOGains:
        del motor, w0, i_dq
        return self.gains

    def pi(self, motor, w0, i_dq):
        del motor, w0, i_dq
        return self.k_p, self.k_i
