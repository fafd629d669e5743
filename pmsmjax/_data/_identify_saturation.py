r"""Identification of a saturation model: the parts of `pmsmjax.identify` that fit the
coefficients of an `AlgebraicSaturation` (`fit` with `"saturation"` or the names in
`SATURATION_FIT`).

The plant of the fit is the package's `PMSM` with `PMSMParams.magnetic` set to an
`AlgebraicSaturation` built from the traced coefficients inside the residual function,
so the derivatives flow through its Newton inversion; the coefficients are fitted in log
space (they are positive) with the exponents `S`, `T`, `U`, `V` held (the user's, or
4, 2, 2, 2 as in `ipm3k5_saturation`).

**What the recordings must excite.** The model is symmetric in $\psi_q$ (it depends on
$|\psi_q|$), so the q axis needs $\max|i_q|$ and the d axis the span of
$i_d \in [-i_{max}, 0]$ (field weakening; the magnet's knee). A recording whose currents
cover less than `min_coverage` of either range gives an `ExcitationWarning` that names
the axis, the range recorded and the range needed, and the coefficients it leaves to
extrapolation; the Gauss-Newton standard deviations, the Fisher-information condition
and the flux uncertainty over the recorded currents (`IdentifyResult.saturation`) say
how well the rest is determined.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._plant._magnetic import AlgebraicSaturation, constant_model
from .._plant._params import Drive
from ._identifiable import IDENTIFIABLE, SATURATION_FIT


#: Default exponents (S, T, U, V) of a fitted `AlgebraicSaturation` (those of the
#: `ipm3k5_sat` preset's model: even, so the model is smooth at zero flux).
DEFAULT_EXPONENTS = (4.0, 2.0, 2.0, 2.0)

#: What each axis's range determines (for the excitation warnings).
_NEEDS = {"d": "a_dd (d-axis saturation; without it a_d0, a_dd and i_f act alike)",
          "q": "a_qq and a_dq (q-axis self- and cross-saturation)"}


def expand(names) -> tuple:
    """`fit` names with `"saturation"` replaced by the six coefficients, once each."""
    out = []
    for n in names:
        out += list(SATURATION_FIT) if n == "saturation" else [n]
    return tuple(dict.fromkeys(out))


def start_model(drive: Drive, saturation, exponents) -> AlgebraicSaturation:
    """The starting `AlgebraicSaturation` of a saturation fit.

    `saturation` (an `AlgebraicSaturation`) if given; else the drive's magnetic model if
    it is one; else a model with the drive's constants as its small-current values
    (`default_start`). `exponents` `(S, T, U, V)` replace the model's when given."""
    m = drive.three_phase_motor
    if saturation is None and isinstance(m.magnetic, AlgebraicSaturation):
        saturation = m.magnetic
    if saturation is not None and not isinstance(saturation, AlgebraicSaturation):
        raise ValueError(f"`identify(saturation=...)` must be an `AlgebraicSaturation` (the "
                         f"starting model); got {type(saturation).__name__}.")
    if exponents is not None:
        exponents = tuple(float(e) for e in exponents)
        if len(exponents) != 4 or not all(math.isfinite(e) and e >= 0 for e in exponents):
            raise ValueError(f"`identify(exponents=...)` must be four numbers (S, T, U, V) "
                             f">= 0; got {exponents!r}.")
    if saturation is None:
        return default_start(drive, exponents or DEFAULT_EXPONENTS)
    if exponents is None:
        return saturation
    return AlgebraicSaturation(**{k: float(getattr(saturation, k)) for k in SATURATION_FIT},
                               **dict(zip("STUV", exponents)),
                               newton_steps=saturation.newton_steps)


def default_start(drive: Drive, exponents=DEFAULT_EXPONENTS,
                  share: float = 0.2) -> AlgebraicSaturation:
    r"""A starting model from the drive's constants `L_d`, `L_q`, `psi_f` (H, H, V s):
    those are its small-current incremental inductances and PM flux, and each
    saturation term carries `share` of the inverse inductance it adds to: the d-axis
    term at $\psi_f$, the q-axis and cross terms at $\psi_q = L_q i_{max}$ (so the
    q-axis inductance falls by about `share` twice at the current limit)."""
    m = drive.three_phase_motor
    S, T, U, V = exponents
    L_d, L_q, psi_f = float(m.L_d), float(m.L_q), float(m.psi_f)
    psi_q = L_q * float(drive.i_max)
    a_d0 = (1.0 - share) / L_d
    a_dd = share / (L_d * (S + 1.0) * psi_f ** S)
    a_q0 = 1.0 / L_q
    a_qq = share * a_q0 / psi_q ** T
    a_dq = share * a_q0 * (U + 2.0) / (psi_f ** (U + 2.0) * psi_q ** V)
    i_f = a_d0 * psi_f + a_dd * psi_f ** (S + 1.0)
    return AlgebraicSaturation(a_d0=a_d0, a_dd=a_dd, a_q0=a_q0, a_qq=a_qq, a_dq=a_dq,
                               i_f=i_f, S=S, T=T, U=U, V=V)


def with_values(model: AlgebraicSaturation, values: dict) -> AlgebraicSaturation:
    """`model` with its coefficients in `values` replaced (traced; no validation)."""
    for name in SATURATION_FIT:
        if name in values:
            model = eqx.tree_at(lambda s, n=name: getattr(s, n), model, values[name])
    return model


def set_magnetic(drive: Drive, model) -> Drive:
    """`drive` whose motor's `magnetic` is `model` (traced inside the fit)."""
    return eqx.tree_at(lambda d: d.motor.magnetic, drive, model, is_leaf=lambda x: x is None)


def fitted_drive(drive: Drive, model: AlgebraicSaturation) -> Drive:
    """`drive` with the fitted magnetic model, and its small-current incremental
    inductances and PM flux as the constants L_d, L_q, psi_f the drive deploys."""
    from .._plant._params import replace_params

    model = AlgebraicSaturation(**{k: float(getattr(model, k)) for k in SATURATION_FIT},
                                S=model.S, T=model.T, U=model.U, V=model.V,
                                newton_steps=model.newton_steps)
    L_d, L_q, psi_f = constant_model(model, "small-current")
    return set_magnetic(replace_params(drive, L_d=L_d, L_q=L_q, psi_f=psi_f), model)


def recorded_currents(recs) -> tuple[np.ndarray, np.ndarray]:
    """The recorded currents in rotor coordinates (A): `(i_d, i_q)`, all recordings."""
    i_d, i_q = [], []
    for r in recs:
        c, s = np.cos(np.asarray(r.theta, float)), np.sin(np.asarray(r.theta, float))
        i_ab = np.asarray(r.i_ab, float)
        i_d.append(c * i_ab[:, 0] + s * i_ab[:, 1])
        i_q.append(c * i_ab[:, 1] - s * i_ab[:, 0])
    return np.concatenate(i_d), np.concatenate(i_q)


def coverage(recs, i_max: float, min_coverage: float) -> tuple[dict, list[str]]:
    """The recorded current ranges (0.5 and 99.5 percentiles, so that noise spikes do not
    count), the fractions of the needed ranges they cover, and the excitation warnings.

    Needed: i_d over [-i_max, 0] and |i_q| up to i_max (A)."""
    i_d, i_q = recorded_currents(recs)
    lo_d, hi_d = (float(v) for v in np.percentile(i_d, [0.5, 99.5]))
    lo_q, hi_q = (float(v) for v in np.percentile(i_q, [0.5, 99.5]))
    q_abs = float(np.percentile(np.abs(i_q), 99.5))
    frac_d = (min(hi_d, 0.0) - max(lo_d, -i_max)) / i_max if lo_d < 0 else 0.0
    frac_q = min(q_abs / i_max, 1.0)
    info = {"i_d_A": [lo_d, hi_d], "i_q_A": [lo_q, hi_q], "i_max_A": float(i_max),
            "coverage_d": max(frac_d, 0.0), "coverage_q": frac_q,
            "min_coverage": float(min_coverage)}
    msgs = []
    if frac_d < min_coverage:
        msgs.append(
            f"the recorded d-axis current spans {lo_d:.3g}..{hi_d:.3g} A, "
            f"{100 * max(frac_d, 0.0):.0f} % of the range {-i_max:.3g}..0 A a saturation "
            f"model needs (at least {100 * min_coverage:.0f} %): {_NEEDS['d']} is not "
            f"identifiable from it (the flux outside the recorded currents is "
            f"extrapolated); record i_d steps "
            f"down to {-min_coverage * i_max:.3g} A or below, at speed.")
    if frac_q < min_coverage:
        msgs.append(
            f"the recorded q-axis current reaches |i_q| = {q_abs:.3g} A, "
            f"{100 * frac_q:.0f} % of the current limit {i_max:.3g} A a saturation model "
            f"needs (at least {100 * min_coverage:.0f} %): {_NEEDS['q']} are not "
            f"identifiable from it (the flux outside the recorded currents is "
            f"extrapolated); record i_q steps "
            f"up to {min_coverage * i_max:.3g} A or beyond, at speed.")
    return info, msgs


def grid(info: dict, n: int = 21) -> tuple[np.ndarray, np.ndarray]:
    """An `n` x `n` current grid (A) over the recorded range (at least 5 % of i_max wide
    per axis, so that a map of a recording at one current still has a grid)."""
    w = 0.05 * info["i_max_A"]
    axes = []
    for lo, hi in (info["i_d_A"], info["i_q_A"]):
        if hi - lo < w:
            lo, hi = 0.5 * (lo + hi) - 0.5 * w, 0.5 * (lo + hi) + 0.5 * w
        axes.append(np.linspace(lo, hi, n))
    return axes[0], axes[1]


def flux_uncertainty(model_of_x, x, cov_x, info: dict, psi_scale: float, n: int = 11
                     ) -> dict:
    """The 1-sigma uncertainty of the fitted flux (V s) over the recorded currents, from
    the parameters' covariance `cov_x` (log-space): its largest value per axis, and
    relative to `psi_scale` (V s, the PM flux)."""
    i_d, i_q = grid(info, n)
    dd, qq = np.meshgrid(i_d, i_q, indexing="ij")
    cur = jnp.stack([jnp.asarray(dd.ravel()), jnp.asarray(qq.ravel())], -1)
    jac = np.asarray(jax.jacfwd(lambda y: model_of_x(y).flux_dq(cur))(x))  # (N, 2, p)
    var = np.einsum("nkp,pr,nkr->nk", jac, cov_x, jac)
    std = np.sqrt(np.maximum(var, 0.0)).max(axis=0)
    return {"psi_d_std_Vs": float(std[0]), "psi_q_std_Vs": float(std[1]),
            "relative_to_psi_f": float(std.max() / psi_scale)}


def flux_map_rows(model, info: dict, n: int = 21) -> np.ndarray:
    """`(n*n, 4)` rows `i_d, i_q, psi_d, psi_q` (A, A, V s, V s) of `model` over the
    recorded current range."""
    i_d, i_q = grid(info, n)
    dd, qq = np.meshgrid(i_d, i_q, indexing="ij")
    psi = np.asarray(model.flux_dq(jnp.stack([jnp.asarray(dd), jnp.asarray(qq)], -1)))
    return np.stack([dd.ravel(), qq.ravel(), psi[..., 0].ravel(), psi[..., 1].ravel()], -1)


def write_flux_map(path, rows: np.ndarray) -> None:
    """A flux-map CSV (header `i_d,i_q,psi_d,psi_q`; A, A, V s, V s)."""
    from .._files import atomic_write

    body = "\n".join(",".join(repr(float(v)) for v in row) for row in rows)
    atomic_write(path, "i_d,i_q,psi_d,psi_q\n" + body + "\n")


def saturation_table(model: AlgebraicSaturation) -> str:
    """The motor file's `[saturation]` table of an `AlgebraicSaturation` (TOML text; the
    keys model, a_d0, a_dd, a_q0, a_qq, a_dq, i_f, S, T, U, V)."""
    lines = ["[saturation]", 'model = "algebraic"  # AlgebraicSaturation (Hinkkanen 2017 '
             '+ magnet current)']
    for k in SATURATION_FIT:
        lines.append(f"{k} = {float(getattr(model, k))!r}  # {IDENTIFIABLE[k][0]}")
    for k in "STUV":
        lines.append(f"{k} = {float(getattr(model, k))!r}")
    return "\n".join(lines) + "\n"


class FluxState(eqx.Module):
    """State of the fit's flux-linkage plant: flux (V s), angle (rad), speed (rad/s)."""

    psi_d: jnp.ndarray
    psi_q: jnp.ndarray
    theta: jnp.ndarray
    w_m: jnp.ndarray


def flux_rates(plant, model: AlgebraicSaturation, y: FluxState, args) -> FluxState:
    r"""The plant's equations with the flux linkage as the state:
    $d\psi/dt = u_{dq} - R_s i(\psi) - \omega J\psi$, $i(\psi)$ the model's explicit
    direction (`AlgebraicSaturation.current`), the inverter's dead-time error at that
    current when `plant.inverter` models it, and the torque and mechanics of `PMSM`.
    The same model as `PMSM` with `magnetic=model` (which keeps the current as its state
    and inverts the model by Newton's method at every evaluation; tested equal), at a
    fraction of the cost."""
    from .._plant._inverter import dead_time_error_ab
    from .._plant._motor import cos_sin

    p, mech = plant.motor, plant.mechanics
    i_d, i_q = model.current(y.psi_d, y.psi_q)
    c, s = cos_sin(y.theta)
    u_a, u_b = args.u_ab[..., 0], args.u_ab[..., 1]
    if plant._dead_time:
        du_a, du_b = dead_time_error_ab(plant.inverter.u_dt, plant.inverter.i_dt,
                                        c * i_d - s * i_q, s * i_d + c * i_q)
        u_a, u_b = u_a - du_a, u_b - du_b
    u_d, u_q = c * u_a + s * u_b, c * u_b - s * u_a
    w = y.w_m
    dpsi_d = u_d - p.R_s * i_d + w * y.psi_q
    dpsi_q = u_q - p.R_s * i_q - w * y.psi_d
    tau_M = 1.5 * p.n_p * (y.psi_d * i_q - y.psi_q * i_d)
    dw = args.free * p.n_p * (tau_M - mech.B * w / p.n_p - args.tau_L) / mech.J
    return FluxState(psi_d=dpsi_d, psi_q=dpsi_q, theta=w, w_m=dw)


def simulate_segments(plant, model: AlgebraicSaturation, seg, n_substeps: int,
                      measured: bool = False):
    """Model current (n, m, 2) and speed (n, m) after each step of each segment, on the
    flux-linkage plant (`flux_rates`): each segment starts from the flux of its measured
    current (the model's Newton inversion, derivatives flowing through it); `measured`:
    the rotor moves as recorded (`_identify.motion_step`)."""
    from .._plant._motor import PlantInput, cos_sin
    from .._sim._integrate import RK4, integrate
    from ._identify_motion import motion_step

    def field(t, y, args):
        del t
        return flux_rates(plant, model, y, args)

    def one(i0, th0, w0, u, tau, th, w, acc):
        c, s = cos_sin(th0)
        psi_d, psi_q, *_ = model.flux_and_inductance(c * i0[0] + s * i0[1],
                                                     c * i0[1] - s * i0[0])
        y0 = FluxState(psi_d=psi_d, psi_q=psi_q, theta=th0, w_m=w0)

        def step(y, x):
            uk, tk, thk, wk, ak = x
            y, f, args = motion_step(field, y, PlantInput(u_ab=uk, tau_L=tk), thk, wk, ak,
                                     measured)
            y = integrate(f, y, args, seg.T_s, solver=RK4(), n_substeps=n_substeps)
            i_d, i_q = model.current(y.psi_d, y.psi_q)
            c, s = cos_sin(y.theta)
            return y, (jnp.stack([c * i_d - s * i_q, s * i_d + c * i_q]), y.w_m)

        return jax.lax.scan(step, y0, (u, tau, th, w, acc))[1]

    return jax.vmap(one)(seg.i0_ab, seg.th0, seg.w0, seg.u, seg.tau_L, seg.th, seg.w, seg.acc)
