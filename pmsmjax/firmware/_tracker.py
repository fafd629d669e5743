"""C for `SpeedFromAngle`: the wrapped observer's own C step, then the type-2 tracking
loop on its angle (`pmsmjax.observers._speed_tracker`), whose speed becomes the step's
`w_hat`, as `replay` computes it."""

from __future__ import annotations

import dataclasses

from ..observers._speed_tracker import SpeedFromAngle
from ._c import CObserver, lit


def emit(observer: SpeedFromAngle, T_s: float) -> CObserver:
    from ._emit import UnsupportedObserverError, emitter_for

    inner = observer._inner()
    emitter = emitter_for(type(inner))
    if emitter is None:
        raise UnsupportedObserverError(
            f"export-c has no C emitter for the observer inside SpeedFromAngle "
            f"({type(inner).__name__})")
    obs = emitter(inner, T_s)
    k_p, k_i = (float(g) for g in observer.gains())
    helpers = obs.helpers + f"""
/* the wrapped observer's step ({obs.name}) */
static void pmsm_obs_inner_step(pmsm_obs_state *s, const pmsm_real i_ab[2],
                                const pmsm_real u_ab_prev[2], pmsm_real *theta_hat,
                                pmsm_real *w_hat)
{{
{obs.step}
}}
"""
    step = f"""    pmsm_real pred, eps;
    pmsm_obs_inner_step(s, i_ab, u_ab_prev, theta_hat, w_hat);
    pred = s->trk_theta + {lit(T_s)} * s->trk_w;
    eps = pmsm_wrap(*theta_hat - pred);
    s->trk_w = s->trk_w + {lit(T_s * k_i)} * eps;
    s->trk_theta = pmsm_wrap(pred + {lit(T_s * k_p)} * eps);
    *w_hat = s->trk_w;"""
    doc = obs.doc + (
        "",
        "w_hat is the speed of theta_hat through a type-2 tracking loop (SpeedFromAngle):",
        "  pred = trk_theta + T_s trk_w,  eps = wrap(theta_hat - pred),",
        "  trk_w += T_s k_i eps,  trk_theta = wrap(pred + T_s k_p eps),  w_hat = trk_w,",
        f"  k_p = 2 zeta w_track = {k_p!r} rad/s, k_i = w_track^2 = {k_i!r} rad/s^2.",
    )
    return dataclasses.replace(
        obs, title=obs.title + ", speed from its angle (SpeedFromAngle)", doc=doc,
        fields=obs.fields + (("pmsm_real trk_theta", "tracking loop's angle (rad)"),
                             ("pmsm_real trk_w", "tracking loop's speed = w_hat (rad/s)")),
        helpers=helpers, init=obs.init + "\n    s->trk_theta = theta0;\n    s->trk_w = w0;",
        step=step)
