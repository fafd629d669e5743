r"""The inverter's dead-time compensation in C: what `pmsmjax replay(..., inverter=...)`
(`--voltage commanded`) hands the observer, for firmware that knows its commanded voltage.

The observer's voltage for the period $[t_{k-1}, t_k)$ is the commanded one less the
inverter error model averaged over the measured currents at the period's two ends
(`pmsmjax._plant._inverter.observer_voltage`),

$$u_{obs} = u^*_{k-1} - \tfrac12\big(\Delta u(i_{k-1}) + \Delta u(i_k)\big),\qquad
\Delta u = \mathrm{clarke}\big(u_{dt}\tanh(i_x / i_{dt})\big)_{x=a,b,c}$$

(or $u_{dt}\,\mathrm{sign}(i_x)$ for the hard model, $i_{dt} = 0$), with no compensation
at the first sample (there is no period before it; replay hands the observer zero). The
generated step keeps $\Delta u(i_k)$ for the next step, so it evaluates the model once per
sample (three `tanh`, or three comparisons for the hard model). `compensation(inverter)`
gives the pieces `_emit` wraps around a family's step, or None for an ideal inverter.
"""

from __future__ import annotations

import dataclasses
import math

from .._plant._params import Inverter
from ._c import lit, scalar


@dataclasses.dataclass(frozen=True)
class Compensation:
    """The dead-time compensation as C text: `u_dt` (V), `i_dt` (A; 0: hard), the state
    `fields`, the `init` lines, the `helpers` (the error model) and the `doc` lines."""

    u_dt: float
    i_dt: float
    fields: tuple[tuple[str, str], ...]
    init: str
    helpers: str
    doc: tuple[str, ...]

    @property
    def hard(self) -> bool:
        return self.i_dt == 0.0

    @property
    def model(self) -> str:
        """The model in words, with its values."""
        if self.hard:
            return f"hard, u_dt sign(i_x) with u_dt = {self.u_dt!r} V"
        return f"smooth, u_dt tanh(i_x / i_dt) with u_dt = {self.u_dt!r} V, i_dt = {self.i_dt!r} A"


_FIELDS = (
    ("pmsm_real dt_e_prev[2]", "inverter error model at the previous sample's current (V)"),
    ("int dt_started", "0 until the first sample has been seen (no compensation there)"),
)

_INIT = """    s->dt_e_prev[0] = PMSM_R(0.0);
    s->dt_e_prev[1] = PMSM_R(0.0);
    s->dt_started = 0;"""

#: `pmsm_obs_step` with the compensation: the family's step is `pmsm_obs_observe`.
STEP = """    pmsm_real e[2], u_obs[2];
    pmsm_dead_time_error(i_ab, e);
    if (s->dt_started) {   /* u* less the mean of the error at the period's two ends */
        u_obs[0] = u_ab_prev[0] - PMSM_R(0.5) * (s->dt_e_prev[0] + e[0]);
        u_obs[1] = u_ab_prev[1] - PMSM_R(0.5) * (s->dt_e_prev[1] + e[1]);
    } else {               /* the first sample: no period before it */
        u_obs[0] = u_ab_prev[0];
        u_obs[1] = u_ab_prev[1];
    }
    s->dt_e_prev[0] = e[0];
    s->dt_e_prev[1] = e[1];
    s->dt_started = 1;
    pmsm_obs_observe(s, i_ab, u_obs, theta_hat, w_hat);"""


def compensation(inverter: Inverter | None) -> Compensation | None:
    """The compensation of `inverter`'s dead-time model (`u_dt`, `i_dt`; concrete values),
    or None when it has none (`None`, or `u_dt` unset or 0: the step then expects the
    applied voltage)."""
    if inverter is None or inverter.dead_time == "none":
        return None
    if not isinstance(inverter, Inverter):
        raise ValueError(f"`export_c(inverter=...)` must be a `pmsmjax.Inverter` (e.g. "
                         f"`drive.inverter`) or None; got {type(inverter).__name__}.")
    u_dt, i_dt = scalar(inverter.u_dt), scalar(inverter.i_dt)
    if i_dt == 0.0:
        phase = ("x > PMSM_R(0.0) ? PMSM_DT_U : (x < PMSM_R(0.0) ? -PMSM_DT_U : "
                 "PMSM_R(0.0))")
        defines = f"#define PMSM_DT_U {lit(u_dt)} /* V */"
    else:
        phase = "PMSM_DT_U * PMSM_TANH(x / PMSM_DT_I)"
        defines = f"#define PMSM_DT_U {lit(u_dt)} /* V */\n#define PMSM_DT_I {lit(i_dt)} /* A */"
    helpers = f"""/* inverter dead-time error model (commanded minus applied, per phase) */
{defines}
static pmsm_real pmsm_dead_time_phase(pmsm_real x)
{{
    return {phase};
}}

/* its alpha-beta vector at the current i_ab: amplitude-invariant Clarke of the phases */
static void pmsm_dead_time_error(const pmsm_real i_ab[2], pmsm_real e[2])
{{
    pmsm_real ea = pmsm_dead_time_phase(i_ab[0]);
    pmsm_real eb = pmsm_dead_time_phase(PMSM_R(-0.5) * i_ab[0] + {lit(0.5 * math.sqrt(3.0))}
                                        * i_ab[1]);
    pmsm_real ec = pmsm_dead_time_phase(PMSM_R(-0.5) * i_ab[0] - {lit(0.5 * math.sqrt(3.0))}
                                        * i_ab[1]);
    e[0] = {lit(2.0 / 3.0)} * (ea - PMSM_R(0.5) * (eb + ec));
    e[1] = (eb - ec) / {lit(math.sqrt(3.0))};
}}
"""
    comp = Compensation(u_dt=u_dt, i_dt=i_dt, fields=_FIELDS, init=_INIT, helpers=helpers,
                        doc=())
    doc = (
        "Dead-time compensation (PMSM_OBS_DEAD_TIME_COMPENSATION 1), as `pmsmjax replay",
        "--voltage commanded` does it: the observer is handed u_ab_prev (COMMANDED) less",
        "(du(i_(k-1)) + du(i_k)) / 2, du the amplitude-invariant Clarke transform of the",
        "inverter's per-phase error model, none at the first sample:",
        f"  {comp.model}.",
        "The step keeps du(i_k) for the next one. Its cost (three "
        + ("comparisons" if i_dt == 0.0 else "tanh") + " per step) is not in",
        "the measured cost above.",
    )
    return dataclasses.replace(comp, doc=doc)
