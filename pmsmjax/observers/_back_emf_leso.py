r"""The machinery shared by li's back-EMF LESOs (`_li_leso`: C-LESO, GI-LESO, FA-LESO):
`AbstractBackEMFLESO`, a linear extended-state observer of the equivalent back-EMF,
integrated exactly over each sampling period, with a quadrature PLL (`_pll`), in the
observer contract (running, design, error coordinates).

**The observer in one form.** The LESO of li-fa-leso (9) estimates the extended state
$x_2 = -e_{ab}/L_q$ of the model $L_q\,di_{ab}/dt = u_{ab} - R_s i_{ab} - e_{ab}$ and
returns $\hat e_{ab} = -\hat L_q\hat x_2$ (10). Every observer here is that LESO with
$\hat x_1$ written as

$$\dot{\hat x}_1 = \frac{\dot\lambda}{\hat L_q} + \hat x_2 + D_1\varepsilon_1,\qquad
\dot\lambda = u_{ab} - \hat R_s i_{ab},\qquad \varepsilon_1 = \hat x_1 - i_{ab},$$

and the rest of its state $s$ linear in $\varepsilon_1$: $\dot s = A_s s + B_s\varepsilon_1$,
$\hat x_2 = C_s s + D_x\varepsilon_1$ (the $-\mu\hat x_1$ of (9) is $-\mu i - \mu
\varepsilon_1$; its $-\mu\varepsilon_1$ is in $D_1$). A subclass gives
`_matrices(w_hat) -> (A_s, B_s, C_s, D_x, D_1)`. Every matrix is made of $2\times2$
blocks $aI + bJ$ (`blk`; complex coefficients $a + jb$ acting on the space vector), so
the observers are rotation invariant and their transfer functions are complex functions
of $s$: `transfer_function`.

**Discretisation** (at $t_k$ with $i_k$ and the voltage held over $[t_{k-1}, t_k)$):

- $\Delta\lambda = T_s u - \tfrac12 T_s\hat R_s(i_{k-1} + i_k)$: the voltage exactly (ZOH),
  the resistive drop by the trapezoid rule (as zhang2022's flux observers);
- the whole observer ($\hat x_1$ and $s$, a linear system driven by the current and by
  $\dot\lambda$) is integrated *exactly* over the interval with its inputs described in
  the frame that turns at the speed estimate $\hat\omega_{k-1}$: the current as
  $i(t) = e^{\hat\omega tJ}(i_{k-1} + t\delta)$ with $\delta$ chosen so that it ends at
  $i_k$ (a first-order hold in the turning frame), $\dot\lambda$ as
  $e^{\hat\omega tJ}c$ with $c$ chosen so that its integral is $\Delta\lambda$. In that
  turning frame the inputs are polynomials in $t$, so the exact solution needs only
  $e^X$, $\varphi_1(X)$, $\varphi_2(X)$ of the observer's own matrix
  $X = (A_o - j\hat\omega I)T_s$ in complex form (`_transition`; size $1 + n_s/2$: 2 for
  the C-LESO and FA-LESO, 4 for the GI-LESO), computed by `_matrix_functions`: as pairs
  of complex numbers for the $2\times2$ case (`phi_pair_apply`); the GI-LESO writes its
  transition as one action $\varphi_2(X)v$ on the non-zero entries of its $X$
  (`GILESOObserver._transition_c`, `phi2_action`). Exact to round-off far beyond the
  designs' $|X| \approx 0.2$ at $T_s = 100\,\mu$s (`_propagator` assembles the real
  transition matrix; the tests check it against `scipy.linalg.expm` of the real
  augmented system, and `jax.grad` through a replay against finite differences). The
  observer's own dynamics (at a given speed estimate) are integrated exactly, so they
  stay stable for any bandwidth and $T_s$ (only the PLL's update is explicit); the
  one-step Jacobian in error coordinates is $I + T_sA + O(T_s^2)$ (the contract test).

In steady state at constant speed every signal turns at $\omega = \hat\omega$, and then
the rotating hold is exact: the discrete observer has exactly the continuous steady state,
so its gain and phase at the fundamental are those of the continuous transfer functions
(17), (26), (29) with no discretisation error; at harmonics $h\omega$ the hold is not
exact and the discrete response departs from them by $O((h - 1)\omega T_s)$
(`pmsmjax.analysis.bemf_response` computes it from this step).

**Error coordinates** (`error_rhs`): $\varepsilon_1$ and $s$ in the true rotor frame minus
their designed steady state at the true speed and current (`steady_state`), then
$\tilde\theta = \theta - \hat\theta$ and $\tilde\omega = \omega - \hat\omega$. The designed
equilibrium is $\varepsilon_1 = s = 0$, $\tilde\omega = 0$ and $\tilde\theta$ equal to the
observer's phase lag at the fundamental plus the parameter-mismatch offset
(`designed_error`): zero for the FA-LESO with a matched model, $-\arg G(j\omega)$
otherwise.
**Saturated machines** (`with_magnetic`, docs/observers.md). The model is $\hat L_q$ in
the current dynamics and the extended flux $\hat\psi_f + (\hat L_d - \hat L_q)\hat i_d$
of the PLL's speed feed; the LESO gains ($\omega_0$, $K_r$, ... ) are fixed at
construction and kept. The scheduled model takes the map's apparent $L_d$, $L_q$,
$\psi_f$ at the measured current in the previous estimate's frame: with the apparent
$L_q$ ($\psi_q = L_q i_q$ exactly) the steady-state back-EMF $u - R_s i - L_q\,di/dt$ is
$\omega J e^{\theta J}[\psi_d(i) - L_q i_d, 0]$, along the q axis, so the model's
extended back-EMF is the map's and the static error from saturation vanishes (a
designed phase lag, the C-LESO's and GI-LESO's, stays). The $L_q\,di/dt$ term uses the
apparent, not the incremental, inductance: right in steady state, approximate in
transients.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from .._frames import back_emf_angle, cos_sin, rotate, wrap_angle
from .._plant._params import PMSMParams
from .._validate import check_positive
from ._base import (
    AbstractObserver,
    Estimate,
    Measurement,
    OperatingPoint,
    PlantPoint,
)
from ._matrix_functions import phi_pair_apply
from ._pll import PLL_UNITS, W_MIN_PU, QuadraturePLL


def blk(a, b=0.0):
    """The 2x2 block a I + b J."""
    a = jnp.asarray(a)
    b = jnp.asarray(b, a.dtype) + 0.0 * a
    return jnp.stack([jnp.stack([a, -b]), jnp.stack([b, a])])


def _rot_blocks(x, theta):
    """Rotate each consecutive 2-vector of `x` (shape (2m,)) by `theta`."""
    return rotate(x.reshape(-1, 2), theta).reshape(-1)


def _to_complex(M):
    """A real matrix of aI + bJ blocks -> the complex matrix of a + jb."""
    return M[0::2, 0::2] + 1j * M[1::2, 0::2]


def _x2(C, Dx, s, eps):
    r"""$\hat x_2 = C s + D_x\varepsilon_1$ on the real layout (2-vectors) for real
    coefficients `C` (one per complex state in `s`) and `Dx`, written out; terms with a
    Python zero coefficient are left out."""
    C = tuple(C) if isinstance(C, (tuple, list)) else (C,)
    terms = [c * v for c, v in zip(C + (Dx,), [s[2 * j:2 * j + 2] for j in range(len(C))]
                                    + [eps]) if not (isinstance(c, (int, float)) and c == 0)]
    return sum(terms[1:], terms[0])


def _cplx(v):
    """A real vector of consecutive 2-vectors -> the complex vector."""
    return v[0::2] + 1j * v[1::2]


def _real(z):
    """A complex vector -> the real vector of consecutive (re, im) pairs."""
    return jnp.stack([z.real, z.imag], -1).reshape(-1)


def _real_layout(out):
    """A transition's result (`_transition_c`: its complex components, or the real
    layout of consecutive (re, im) pairs already) in the real layout."""
    out = jnp.stack(out) if isinstance(out, tuple) else out
    return _real(out) if jnp.iscomplexobj(out) else out


class LESOState(eqx.Module):
    """State of the li-fa-leso observers.

    - `s`: internal states (C-LESO: $\\hat x_2$ (A/s); GI-LESO: $\\hat x_2$, $r$ (A s^2),
      $q$ (A s); FA-LESO: $z$ (A/s)), stationary frame, `(n_s,)`.
    - `x1`: estimated current $\\hat x_1$ (A, stationary frame).
    - `theta`: PLL angle (rad, wrapped); `w`: PLL speed (rad/s, electrical).
    - `i_prev`: current sampled at the previous instant (A).
    - `started`: False until the first sample has been seen.
    """

    s: jnp.ndarray
    x1: jnp.ndarray
    theta: jnp.ndarray
    w: jnp.ndarray
    i_prev: jnp.ndarray
    started: jnp.ndarray


_EXTRAS = {"e_ab_hat": "V, estimated equivalent back-EMF li-fa-leso (10), stationary "
                       "frame (2,)"}


class AbstractBackEMFLESO(AbstractObserver):
    """Shared machinery of the li-fa-leso observers (see the module docstring).

    Subclasses give `_matrices(w_hat) -> (A_s, B_s, C_s, D_x, D_1)`, the design
    (`_own_design`) and the names of their internal states.
    """

    motor: eqx.AbstractVar[PMSMParams]
    pll: eqx.AbstractVar[QuadraturePLL]
    n_s: ClassVar[int] = 2
    #: The PLL design's floor, `W_MIN_PU` (below it the loop gain fades: `QuadraturePLL`,
    #: "Low speed and zero speed"); on `li_dtp` every validation run that takes a
    #: sensored drive below it reaches 1 % of rated speed under its load step, and each
    #: li observer loses all of them with its paper's design, with the floor at 0.01 p.u.
    #: too (docs/tuning.md, "The low-speed limit").
    low_speed_limit_pu: ClassVar[float] = W_MIN_PU
    tunable_kinds: ClassVar[dict[str, str]] = {"w0": "estimator", "w_pll": "tracking",
                                               "zeta_pll": "damping"}
    extras: ClassVar[dict[str, str]] = _EXTRAS

    # --- the model --------------------------------------------------------------------
    @abc.abstractmethod
    def _matrices(self, w_hat):
        """`(A_s, B_s, C_s, D_x, D_1)` at speed estimate `w_hat` (rad/s)."""

    @abc.abstractmethod
    def _own_design(self) -> dict:
        ...

    def transfer_function(self, s, w_hat):
        r"""The continuous-time transfer function $\hat e_{ab}/e_{ab}$ (complex) at the
        complex frequency(ies) `s` (rad/s) for the speed estimate `w_hat` (rad/s), from the
        observer's own matrices: $G = H/(H + D_1 - s)$ with
        $H(s) = C_s(sI - A_s)^{-1}B_s + D_x$ (li-fa-leso (14) in this realisation)."""
        A, B, C, Dx, D1 = (_to_complex(M) for M in self._matrices(jnp.asarray(w_hat, float)))
        s = jnp.asarray(s, complex)

        def one(sv):
            n = A.shape[0]
            H = C @ jnp.linalg.solve(sv * jnp.eye(n, dtype=complex) - A, B) + Dx
            return (H / (H + D1 - sv))[0, 0]

        return jax.vmap(one)(s.reshape(-1)).reshape(s.shape)

    def _psi_ex(self, i_ab, theta):
        """Model extended flux $\\hat\\psi_f + (\\hat L_d - \\hat L_q)\\hat i_d$ (V s) at
        the d current of `i_ab` (A) on the axis at `theta` (rad)."""
        # park(i_ab, theta)'s d component, written with cos and sin of `theta` (which the
        # PLL computes too: one evaluation for both)
        c, s = cos_sin(theta)
        i_d = i_ab[..., 0] * c + i_ab[..., 1] * s
        return self.motor.extended_flux(i_d)

    # --- running ----------------------------------------------------------------------
    def init(self, theta0=0.0, w0=0.0) -> LESOState:
        theta0, w0 = jnp.asarray(theta0), jnp.asarray(w0)
        dtype = jnp.result_type(theta0, w0, float)
        return LESOState(s=jnp.zeros(self.n_s, dtype), x1=jnp.zeros(2, dtype),
                         theta=wrap_angle(theta0.astype(dtype)), w=w0.astype(dtype),
                         i_prev=jnp.zeros(2, dtype), started=jnp.asarray(False))

    def _complex_system(self, w_hat):
        r"""The observer in complex form (`_to_complex` of `_matrices`) at speed estimate
        `w_hat`, as `(Ao, g_i, C, Dx)`: $\dot y = A_o y + g_i i + g_c\dot\lambda$ with
        $y = [x_1, s]$, $A_o = [[D_x + D_1, C], [B, A]]$, $g_i = -[D_x + D_1; B]$, and
        $\hat x_2 = Cs + D_x\varepsilon_1$. Subclasses write it from their coefficients
        directly (complex scalars, or constant patterns times scalars), so that the step
        builds no block matrices; this generic version slices `_matrices`."""
        A, B, C, Dx, D1 = (_to_complex(M) for M in self._matrices(w_hat))
        K = Dx + D1
        return jnp.block([[K, C], [B, A]]), -jnp.concatenate([K, B])[:, 0], C[0], Dx[0, 0]

    def _transition_c(self, w_hat, T_s, y, i0, dl, c, rot=None):
        r"""`_transition` in complex form: the complex state `y` one period on
        (stationary frame), from the complex current `i0`, its hold slope `dl` and the
        voltage-integral rate `c`; `rot` is $e^{j\hat\omega T_s}$ if the caller has it.
        Here for $p = 2$ (the two components as a tuple); an observer with a larger state
        writes its own, and may return the real layout (`_real_layout`)."""
        T = jnp.asarray(T_s, jnp.real(i0).dtype)
        Ao, g_i, _, _ = self._complex_system(w_hat)
        jwT = jax.lax.complex(jnp.zeros_like(T), -jnp.asarray(w_hat, T.dtype) * T)
        inv_lq = 1.0 / self.motor.L_q
        if isinstance(Ao, tuple):  # p = 2: the four entries as complex scalars
            (k, cc), (b, a) = Ao
            mu = 0.5 * (k + a) * T + jwT
            n00, n01, n10 = 0.5 * (k - a) * T, cc * T, b * T  # N = X - mu I, traceless
            E0, E1, E2 = phi_pair_apply(mu, n00 * n00 + n01 * n10)
            # as vectors of the two components (one kernel for the whole transition;
            # written on scalars XLA computed it once for each component)
            yv = jnp.stack(y, -1)
            g0 = jnp.stack([T * (g_i[0] * i0 + inv_lq * c), T * (g_i[1] * i0)], -1)
            g1 = (T * T) * (jnp.stack([g_i[0], g_i[1] + 0.0 * g_i[0]], -1) * dl[..., None])
            ua = E0[0][..., None] * yv + E1[0][..., None] * g0 + E2[0][..., None] * g1
            ub = E0[1][..., None] * yv + E1[1][..., None] * g0 + E2[1][..., None] * g1
            out = ua + jnp.stack([n00 * ub[..., 0] + n01 * ub[..., 1],
                                  n10 * ub[..., 0] - n00 * ub[..., 1]], -1)
            rot = jnp.exp(-jwT) if rot is None else rot
            out = rot[..., None] * out
            return out[..., 0], out[..., 1]
        raise NotImplementedError(
            f"{type(self).__name__}: an observer with more than one complex internal state "
            "gives its own `_transition_c` (as `GILESOObserver`).")

    def _transition(self, w_hat, T_s, v):
        r"""The state `[x1, s]` one period after `v = [x1, s, i, delta, c]` (real, `(n_s +
        8,)`), the observer driven by the current $i(t) = e^{\hat\omega tJ}(i +
        t\,\delta)$ and the voltage-integral rate $e^{\hat\omega tJ}c$ (see the module
        docstring), integrated exactly.

        In complex form (`_complex_system`) the observer is $\dot y = A_o y + g_i\,i(t) +
        g_c\,c(t)$ with $y = [x_1, s]$ of size $p = 1 + n_s/2$; in the frame turning at
        $\hat\omega$, $\hat y = e^{-j\hat\omega t}y$, the inputs are a polynomial in $t$,
        so with $X = (A_o - j\hat\omega I)T_s$:
        $y(T_s) = e^{j\hat\omega T_s}[e^X y + T_s\varphi_1(X)(g_i i + g_c c) +
        T_s^2\varphi_2(X)g_i\delta]$. For $p = 2$ (C-LESO, FA-LESO) the three functions
        of $X$ are pairs of complex numbers (`phi_pair`); the GI-LESO evaluates the sum
        as one action on the non-zero entries of its $X$
        (`GILESOObserver._transition_c`). `step` calls `_transition_c` directly (the
        GI-LESO's on the state's real layout)."""
        p = 1 + self.n_s // 2
        z = _cplx(v)
        y = z[:p]
        out = self._transition_c(w_hat, T_s, tuple(y) if p == 2 else y, z[p], z[p + 1],
                                 z[p + 2])
        return _real_layout(out).astype(v.dtype)

    def _complex_scale(self, w_hat):
        """A diagonal scaling of the complex state `[x1, s]` (its units) under which the
        norm of `X` measures the Taylor truncation (`GILESOObserver._transition_c`)."""
        return jnp.ones(1 + self.n_s // 2, jnp.result_type(w_hat, float))

    def _propagator(self, w_hat, T_s):
        """The exact transition matrix over one period, `(n_s + 2, n_s + 8)`: rows of
        `[x1, s]`, columns of `[x1, s, i, delta, c]` (`_transition` of each unit vector;
        for analysis and tests, `step` calls `_transition`)."""
        dtype = jnp.result_type(w_hat, float)
        eye = jnp.eye(self.n_s + 8, dtype=dtype)
        return jax.vmap(lambda v: self._transition(w_hat, T_s, v), out_axes=1)(eye)

    def step(self, state: LESOState, meas: Measurement, T_s):
        self = self._scheduled(state, meas)  # noqa: PLW0642 (the current-scheduled model)
        # the hold and the transition on complex scalars (space vectors), with the
        # coefficients written directly, so that XLA fuses the step into few kernels
        m = self.motor
        dtype = state.x1.dtype
        cx = lambda v: jax.lax.complex(v[..., 0], v[..., 1])  # noqa: E731
        i_k = cx(jnp.asarray(meas.i_ab).astype(dtype))
        u = cx(jnp.asarray(meas.u_ab).astype(dtype))
        i_prev, x1 = cx(state.i_prev), cx(state.x1)
        s = state.s
        s_c = [jax.lax.complex(s[2 * j], s[2 * j + 1]) for j in range(self.n_s // 2)]
        w_hat = state.w
        T = jnp.asarray(T_s, dtype)
        _, _, C, Dx = self._complex_system(w_hat)
        d_lam = T * u - (0.5 * T * m.R_s) * (i_prev + i_k)
        # the rate of lambda held in the turning frame, with the same integral d_lam:
        # int_0^T exp(w t J) c dt = T sinc(w T / 2) exp(w T J / 2) c
        # (one cosine and sine of the half angle serve the hold and the transition's
        # turn e^{j w_hat T} = h^2)
        half = 0.5 * T * w_hat
        cos_h, sin_h = cos_sin(half)
        h = jax.lax.complex(cos_h, sin_h)
        small = jnp.abs(half) < 1e-4  # sin(x)/x = 1 - x^2/6 + x^4/120: below round-off
        half_s = jnp.where(small, 1.0, half)
        sinc = jnp.where(small, 1.0 - half * half / 6.0, sin_h / half_s)
        c = d_lam * jnp.conj(h) / (T * sinc)
        # the current between the samples: turning at w_hat, linear in that frame
        rot = h * h
        delta = (i_k * jnp.conj(rot) - i_prev) / T
        if self.n_s == 2:
            out = self._transition_c(w_hat, T, (x1, s_c[0]), i_prev, delta, c, rot)
        else:  # the state in the real layout (`GILESOObserver._transition_c`)
            out = self._transition_c(w_hat, T, jnp.concatenate([state.x1, state.s]),
                                     i_prev, delta, c, rot)
        # back to the real layout [x1, s] as one array: every consumer reads it (XLA
        # would otherwise duplicate the transition's graph into each of them)
        z = _real_layout(out).astype(dtype)
        x1_new, s_new = z[:2], z[2:]
        i_k = jnp.asarray(meas.i_ab).astype(dtype)
        go = state.started
        # first sample: the estimated current starts at the measured one, the extended
        # states at zero (no back-EMF assumed)
        s_new = jnp.where(go, s_new, jnp.zeros_like(s_new)).astype(state.s.dtype)
        x1_new = jnp.where(go, x1_new, i_k)
        e_hat = -m.L_q * _x2(C, Dx, s_new, x1_new - i_k)
        # the estimate one period earlier, from the previous state (zero before the
        # first two samples: the PLL's acquisition assist is off until then)
        e_prev = -m.L_q * _x2(C, Dx, state.s, state.x1 - state.i_prev)
        theta, w = self.pll.step(state.theta, state.w, e_hat,
                                 lambda th: self._psi_ex(i_k, th), T_s, e_prev=e_prev)
        theta = jnp.where(go, theta, state.theta).astype(state.theta.dtype)
        w = jnp.where(go, w, state.w).astype(state.w.dtype)
        new = LESOState(s=s_new, x1=x1_new, theta=theta, w=w, i_prev=i_k,
                        started=jnp.ones_like(state.started))
        return new, Estimate(theta_hat=theta, w_hat=w, extras={"e_ab_hat": e_hat})

    # --- design -----------------------------------------------------------------------
    def design_parameters(self) -> dict:
        return {**self._own_design(), "w_pll": self.pll.w_pll,
                "zeta_pll": self.pll.zeta_pll, "w_min": self.pll.w_min}

    def with_design(self, **values):
        self._check_design_names(values)
        for k, v in values.items():  # every design parameter here is a positive rate
            check_positive(f"{type(self).__name__}.with_design", k, v,
                           self.design_units[k].split(",")[0])
        pll_values = {k: values.pop(k) for k in list(values) if k in PLL_UNITS}
        obs = self._replace(**values) if values else self
        if pll_values:
            obs = eqx.tree_at(lambda o: [getattr(o.pll, k) for k in pll_values], obs,
                              list(pll_values.values()))
        return obs

    # --- analysis ---------------------------------------------------------------------
    def steady_state(self, w, rho_dq):
        r"""The designed steady state $(\varepsilon_1, s)$ in the frame turning at `w`
        (rad/s) with $\hat\omega = \omega$, for the model back-EMF signal
        $\rho = (\dot\lambda - \hat L_q\,di/dt)/\hat L_q$ (A/s; $= e/L_q = -x_2$ with a
        matched model) given in that frame: solves
        $0 = \rho + C_s s + (D_x + D_1 - \omega J)\varepsilon_1$,
        $0 = (A_s - \omega J)s + B_s\varepsilon_1$."""
        A, B, C, Dx, D1 = self._matrices(w)
        n = self.n_s
        dtype = A.dtype
        wJ1 = blk(0.0 * w, w).astype(dtype)
        wJn = jnp.kron(jnp.eye(n // 2, dtype=dtype), wJ1)
        K = jnp.block([[Dx + D1 - wJ1, C], [B, A - wJn]])
        rhs = jnp.concatenate([-rho_dq, jnp.zeros(n, dtype)])
        sol = jnp.linalg.solve(K, rhs)
        return sol[:2], sol[2:]

    def _rho_steady(self, plant: PMSMParams, w, i_dq):
        """$\\rho$ in the rotor frame at constant speed `w` and rotor-frame current `i_dq`."""
        m = self.motor
        psi = jnp.stack([plant.L_d * i_dq[0] + plant.psi_f, plant.L_q * i_dq[1]])
        J = lambda v: jnp.stack([-v[1], v[0]])  # noqa: E731
        return (w * J(psi) + (plant.R_s - m.R_s) * i_dq - m.L_q * w * J(i_dq)) / m.L_q

    def _steady_truth(self, plant, w, i_dq):
        return self.steady_state(w, self._rho_steady(plant, w, i_dq))

    def error_rhs(self, x, op: OperatingPoint, plant: PMSMParams):
        m = self.motor
        n = self.n_s
        x = jnp.asarray(x)
        a = 2 + n
        w = jnp.asarray(op.w_m, x.dtype)
        i0 = jnp.asarray(op.i_dq, x.dtype)
        th = x[a]  # true angle; the estimated frame is at 0 (rotation invariance)
        w_hat = w - x[a + 1]
        i_ab = i0
        i_dq = rotate(i0, -th)
        eps_s, s_s = self._steady_truth(plant, w, i_dq)
        eps = rotate(x[:2] + eps_s, th)
        s = _rot_blocks(x[2:a] + s_s, th)
        A, B, C, Dx, D1 = self._matrices(w_hat)
        x2_hat = C @ s + Dx @ eps
        e_hat = -m.L_q * x2_hat
        eps_pll = self.pll.error(e_hat, jnp.zeros_like(w), w_hat,
                                 m.extended_flux(i0[0]))
        th_hat_dot, w_hat_dot = self.pll.rates(w_hat, eps_pll)
        J = lambda v: jnp.stack([-v[1], v[0]])  # noqa: E731
        di_ab = th_hat_dot * J(i_ab)
        psi_ab = rotate(jnp.stack([plant.L_d * i_dq[0] + plant.psi_f,
                                   plant.L_q * i_dq[1]]), th)
        di_rel = rotate(di_ab - w * J(i_ab), -th)  # = d i_dq / dt in the rotor frame
        dpsi = w * J(psi_ab) + rotate(jnp.stack([plant.L_d * di_rel[0],
                                                 plant.L_q * di_rel[1]]), th)
        rho = (dpsi + (plant.R_s - m.R_s) * i_ab - m.L_q * di_ab) / m.L_q
        d_eps = rho + x2_hat + D1 @ eps
        d_s = A @ s + B @ eps
        _, (d_eps_s, d_s_s) = jax.jvp(lambda v: self._steady_truth(plant, w, v), (i_dq,),
                                      (di_rel,))
        dx_eps = rotate(d_eps - w * J(eps), -th) - d_eps_s
        d_s_rot = d_s - w * jnp.stack([-s[1::2], s[0::2]], -1).reshape(-1)
        dx_s = _rot_blocks(d_s_rot, -th) - d_s_s
        return jnp.concatenate([dx_eps, dx_s, jnp.stack([w - th_hat_dot, -w_hat_dot])])

    def error_scale(self, op: OperatingPoint, plant: PMSMParams):
        m = self.motor
        w = jnp.asarray(op.w_m, float)
        aw = jnp.abs(w)
        i_mag = jnp.sqrt(jnp.sum(jnp.asarray(op.i_dq) ** 2))
        psi_ref = jnp.abs(m.psi_f) + jnp.abs(m.L_d - m.L_q) * i_mag + m.L_q * i_mag
        w_ref = jnp.maximum(aw, self.pll.w_min)
        rho_ref = jnp.stack([0.0 * w, w_ref * psi_ref / m.L_q])
        eps_s, s_s = self.steady_state(w, rho_ref)
        blocks = jnp.concatenate([eps_s, s_s]).reshape(-1, 2)
        mag = jnp.sqrt(jnp.sum(blocks ** 2, -1))
        mag = jnp.where(mag > 0, mag, 1.0)
        del plant
        return jnp.concatenate([jnp.repeat(mag, 2),
                                jnp.stack([jnp.ones_like(w), jnp.where(aw > 0, aw, 1.0)])])

    def error_state(self, state: LESOState, truth: PlantPoint, plant: PMSMParams):
        th = truth.theta
        i_dq = rotate(truth.i_ab, -th)
        eps_s, s_s = self._steady_truth(plant, truth.w_m, i_dq)
        x_eps = rotate(state.x1 - truth.i_ab, -th) - eps_s
        x_s = _rot_blocks(state.s, -th) - s_s
        return jnp.concatenate([x_eps, x_s, jnp.stack([wrap_angle(th - state.theta),
                                                       truth.w_m - state.w])])

    def observer_state(self, x, truth: PlantPoint, plant: PMSMParams) -> LESOState:
        x = jnp.asarray(x)
        n = self.n_s
        th = truth.theta
        i_ab = jnp.asarray(truth.i_ab, x.dtype)
        i_dq = rotate(i_ab, -th)
        eps_s, s_s = self._steady_truth(plant, truth.w_m, i_dq)
        x1 = i_ab + rotate(x[:2] + eps_s, th)
        s = _rot_blocks(x[2:2 + n] + s_s, th)
        return LESOState(s=s, x1=x1, theta=wrap_angle(th - x[2 + n]),
                         w=truth.w_m - x[3 + n], i_prev=i_ab, started=jnp.asarray(True))

    def designed_error(self, op: OperatingPoint, plant: PMSMParams, n_iter: int = 12):
        r"""The equilibrium of `error_rhs` on the designed branch ($\hat\omega = \omega$,
        $\varepsilon_1$, $s$ at their steady state): the angle error $\tilde\theta$ at
        which the PLL's phase detector is zero, $\tilde\theta = \mathrm{atan2}(\sigma\hat
        e_d, \sigma\hat e_q)$ with $\hat e_{dq}$ the steady-state estimate in the rotor
        frame and $\sigma = \mathrm{sign}\,\omega$. The rotor-frame current
        $e^{-\tilde\theta J}i_0$ depends on $\tilde\theta$ when the model is mismatched,
        so this is iterated (`n_iter` fixed-point steps; exact after one step with a
        matched model). Compiled once per observer (its loop, run op by op, compiled anew
        at every call; the operating point's numbers are its inputs)."""
        return _designed_error(self, jax.tree_util.tree_map(jnp.asarray, op), plant, n_iter)


@eqx.filter_jit
def _designed_error(obs: AbstractBackEMFLESO, op: OperatingPoint, plant: PMSMParams,
                    n_iter: int):
    """`AbstractBackEMFLESO.designed_error`."""
    m = obs.motor
    n = obs.n_s
    w = jnp.asarray(op.w_m, float)
    i0 = jnp.asarray(op.i_dq, w.dtype)
    sg = jnp.sign(w)
    _, _, C, Dx, _ = obs._matrices(w)

    def body(th, _):
        eps_s, s_s = obs._steady_truth(plant, w, rotate(i0, -th))
        e_dq = -m.L_q * (C @ s_s + Dx @ eps_s)
        return -back_emf_angle(e_dq, sg), None  # theta - theta_hat

    th, _ = jax.lax.scan(body, jnp.zeros((), w.dtype), None, length=n_iter)
    return jnp.zeros(n + 4, w.dtype).at[2 + n].set(th)


