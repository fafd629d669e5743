"""The pieces of C text every observer family's emitter builds on: `CObserver` (one
observer as C: state, init, step), `lit` (a number as a C literal), `scalar` (a parameter
leaf as a float), the observer's machine model as C defines and a header line
(`model_defines`, `model_doc`) and `FLUX_STATE_INIT` (the init body of the flux
observers). The families (`_zhang2022`, `_morawiec2023`, `_stumper`, `_li`) import them;
`_emit` puts a family's `CObserver` into the files."""

from __future__ import annotations

import dataclasses
import math

import numpy as np


@dataclasses.dataclass(frozen=True)
class CObserver:
    """One observer as C text (all in terms of `pmsm_real` and the `PMSM_*` math macros).

    - `name`: the registered name; `title`: one line naming the observer and paper.
    - `doc`: lines of the header comment (equations, gains, units).
    - `fields`: `(C declaration, comment)` of the state struct's members.
    - `helpers`: static C functions used by `step` (text).
    - `init`: body of `pmsm_obs_init(s, theta0, w0)`.
    - `step`: body of `pmsm_obs_step(s, i_ab, u_ab_prev, theta_hat, w_hat)`.
    """

    name: str
    title: str
    doc: tuple[str, ...]
    fields: tuple[tuple[str, str], ...]
    helpers: str
    init: str
    step: str


def scalar(x) -> float:
    """A concrete parameter leaf (Python or array scalar) as a float, for generated code."""
    return float(np.asarray(x))


#: `pmsm_obs_init` of the flux observers (zhang2022's and morawiec2023's, same state).
FLUX_STATE_INIT = """    s->psi_ab[0] = PMSM_R(0.0);
    s->psi_ab[1] = PMSM_R(0.0);
    s->theta = pmsm_wrap(theta0);
    s->w = w0;
    s->i_prev[0] = PMSM_R(0.0);
    s->i_prev[1] = PMSM_R(0.0);
    s->started = 0;"""


def lit(x) -> str:
    """A C literal of the number `x` (double text that round-trips), cast to pmsm_real."""
    x = float(x)
    if not math.isfinite(x):
        raise ValueError(f"a generated constant must be finite; got {x!r}.")
    return f"PMSM_R({x!r})"


def model_values(motor) -> tuple[float, float, float, float]:
    """`(R_s, L_d, L_q, psi_f)` of the observer's machine model `motor` as floats (Ohm, H,
    H, V s)."""
    return scalar(motor.R_s), scalar(motor.L_d), scalar(motor.L_q), scalar(motor.psi_f)


def model_defines(motor) -> str:
    """The C defines `PMSM_RS`, `PMSM_LD`, `PMSM_LQ`, `PMSM_PSIF` of the observer's machine
    model `motor` (one a line, no final newline)."""
    R_s, L_d, L_q, psi_f = model_values(motor)
    return (f"#define PMSM_RS {lit(R_s)}\n#define PMSM_LD {lit(L_d)}\n"
            f"#define PMSM_LQ {lit(L_q)}\n#define PMSM_PSIF {lit(psi_f)}")


def model_doc(motor) -> str:
    """The header comment's line naming the observer's machine model `motor`."""
    R_s, L_d, L_q, psi_f = model_values(motor)
    return f"Model: R_s = {R_s!r} Ohm, L_d = {L_d!r} H, L_q = {L_q!r} H, psi_f = {psi_f!r} V s."
