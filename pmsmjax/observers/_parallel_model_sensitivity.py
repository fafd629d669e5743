r"""stumper's sensitivity analysis of the parallel-model estimator (`_parallel_model`):
the angle offsets under errors in the model's resistance and inductance in closed form,
stumper (21)-(32) corrected, and the printed forms of its errata, kept to show them.

- `parallel_model_offset`: the steady-state offset of the raw estimate (16)-(17) under
  model errors, open loop (the current given in rotor coordinates: stumper (31)-(32)
  corrected) or closed loop (the current held in the estimated frame; with the filters,
  `ParallelModelObserver.fast_equilibria`).
- `parallel_model_sensitivity`: the offsets at one instant, stumper (22)-(30); the printed
  (27) lacks a minus sign (`printed=True` returns it).
- `parallel_model_offsets_printed`: stumper (31)-(32) as printed.
- `parallel_model_angle_printed`: the angle rule (16)-(17) as printed, right only at
  positive speed (the estimator uses `parallel_model_angle`).

`tests/test_parallel_model.py` and `tests/test_parallel_model_sensitivity.py` fail on the
printed forms.
"""

from __future__ import annotations

import jax.numpy as jnp

from .._frames import back_emf_angle
from .._plant._params import PMSMParams


def parallel_model_angle_printed(e_P, e_O, phi):
    """stumper (16)-(17) as printed: `-arctan((L rho_dot + R rho - u_P)/(L rho phi_dot +
    u_O)) + phi`, plus pi where `-L rho phi_dot - u_O < 0`. Correct only for positive
    speed (kept to show the erratum)."""
    bar = -jnp.arctan((-e_P) / (-e_O)) + phi
    return jnp.where(e_O >= 0, bar, bar + jnp.pi)


def parallel_model_offset(plant: PMSMParams, dR, dL, w_m, i_dq, *, frame="rotor",
                        dpsi=0.0):
    r"""Closed-form steady-state angle offset $\hat\theta - \theta$ (rad, estimate minus
    true, as stumper (21)) of the raw estimator (16)-(17) under model errors.

    Derivation: in steady state $\dot\rho = 0$, $\dot\phi = \omega$ and
    $u = R i + L_q\,\omega J i + e_{ext}$ (extended back-EMF $\omega\psi_{ext}$ on the q
    axis, $\psi_{ext} = \psi_f + (L_d - L_q)i_d$). The estimator subtracts
    $\hat R i + \hat L\omega J i$, so its back-EMF is, in rotor coordinates,
    $\hat e = [\Delta L\,\omega i_q - \Delta R\,i_d,\ \omega\psi_{ext} - \Delta R\,i_q
    - \Delta L\,\omega i_d]$ with $\Delta R = \hat R - R$, $\Delta L = \hat L - L_q$ (estimate
    minus true), and the offset is the d-axis angle it shows (`back_emf_angle`).

    - `frame="rotor"`: `i_dq` is the current in rotor coordinates (open loop, stumper
      (31)-(32) corrected; `s` = sign of the speed):
      $\Delta\theta = \mathrm{atan2}(s(\Delta R i_d - \Delta L\omega i_q),
      s(\omega\psi_{ext} - \Delta R i_q - \Delta L\omega i_d))$.
    - `frame="estimated"`: `i_dq` is held in the estimated frame (closed loop, what the
      controller's references are): the estimator's equilibrium is where $\hat e$ lies on
      the estimated q axis, $\sin\Delta\theta = (\Delta R i_d - \Delta L\omega i_q)/
      (\omega\psi_{ext})$ (isotropic machine; with saliency $\psi_{ext}$ depends on the
      rotor-frame $i_d$ and is solved by fixed-point steps). NaN where no equilibrium
      exists (|sin| > 1).

    `dpsi`: unused by the angle (the estimator's angle does not depend on $\hat\psi_f$),
    kept so that a mismatch in every model parameter can be passed. Broadcasts over
    `dR` (Ohm), `dL` (H), `w_m` (rad/s, electrical), `i_dq` (A, `(..., 2)`).
    """
    del dpsi
    i_dq = jnp.asarray(i_dq)
    i_d, i_q = i_dq[..., 0], i_dq[..., 1]
    w = jnp.asarray(w_m)
    if frame == "rotor":
        # the angle of the estimator's back-EMF e_hat (rotor coordinates) from the q axis
        e_hat = jnp.stack(jnp.broadcast_arrays(
            dL * w * i_q - dR * i_d, w * plant.extended_flux(i_d) - dR * i_q - dL * w * i_d),
            -1)
        return back_emf_angle(e_hat, jnp.where(w >= 0, 1.0, -1.0))
    if frame == "estimated":
        num = dR * i_d - dL * w * i_q
        x = jnp.zeros_like(num * w)
        for _ in range(8):
            i_d_rot = i_d * jnp.cos(x) - i_q * jnp.sin(x)  # rotor frame: e^{x J} i_dq
            sn = num / (w * plant.extended_flux(i_d_rot))
            x = jnp.where(jnp.abs(sn) <= 1.0, jnp.arcsin(jnp.clip(sn, -1.0, 1.0)), jnp.nan)
        return x
    raise ValueError(f"`parallel_model_offset(frame=...)` must be 'rotor' or 'estimated'; "
                     f"got {frame!r}.")


def parallel_model_sensitivity(u_P, u_O, rho, rho_dot, phi_dot, R, L, dR=0.0, dL=0.0,
                                *, printed=False):
    r"""The angle offsets (rad, estimate minus true, stumper (21) in electrical angle)
    of the raw estimate (16) at one instant, for an inductance error `dL` (H) alone,
    stumper (22)-(25), and for a resistance error `dR` (Ohm) alone, stumper (27)-(30);
    `R` (Ohm), `L` (H): the true values; `u_P`, `u_O` (V), `rho` (A), `rho_dot` (A/s),
    `phi_dot` (rad/s) as in (11)-(14). Positive speed (the rule of (16) without the
    half-turn of (17)). Returns `(offset_L, offset_R)`.

    Derivation: with $a = L\dot\rho + R\rho - u_P$ and $b = -(L\rho\dot\phi + u_O)$ the
    exact angle is that of $(b, a)$; the estimator's is that of $(b - \Delta L\rho\dot
    \phi, a + \Delta L\dot\rho + \Delta R\rho)$, and the angle between two vectors is
    $\mathrm{atan}(v\times\hat v / v\cdot\hat v)$. For $\Delta L$ this is (22)-(25) as
    printed; for $\Delta R$ it is $\mathrm{atan}(-\Delta R\,c_{R1}/(\Delta R\,c_{R2} +
    c_{R3}))$: the printed (27) lacks the minus sign in the numerator (`printed=True`
    returns the printed form).
    """
    a = L * rho_dot + R * rho - u_P
    c3 = (L * rho * phi_dot + u_O) ** 2 + a ** 2
    c_L1 = -u_O * rho_dot + rho * phi_dot * (R * rho - u_P)
    c_L2 = rho * phi_dot * (L * rho * phi_dot + u_O) + rho_dot * a
    c_R1 = rho * (L * rho * phi_dot + u_O)
    c_R2 = rho * a
    off_L = jnp.arctan(dL * c_L1 / (dL * c_L2 + c3))
    sign = 1.0 if printed else -1.0
    off_R = jnp.arctan(sign * dR * c_R1 / (dR * c_R2 + c3))
    return off_L, off_R


def parallel_model_offsets_printed(plant: PMSMParams, dR, dL, w_m, i_dq):
    """stumper (31) and (32) as printed (rad): `(dtheta_L, dtheta_R)`, with
    `n_p phi_M - phi = -atan2(i_q, i_d)` and the paper's K = `psi_f`, omega_M = w_m/n_p.
    Kept to show the errata (see `parallel_model_offset` for the derivation)."""
    i_dq = jnp.asarray(i_dq)
    i_d, i_q = i_dq[..., 0], i_dq[..., 1]
    n_p, K = plant.n_p, plant.psi_f
    rho_sin, rho_cos = -i_q, i_d  # rho sin(n_p phi_M - phi), rho cos(...)
    d_L = jnp.arctan(n_p * rho_sin * dL / (n_p * rho_cos * dL - K / n_p))
    d_R = jnp.arctan(-rho_cos * dR / (rho_sin * dR - K * w_m / n_p))
    return d_L, d_R
