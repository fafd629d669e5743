"""The parallel-model estimator's closed-form equilibria (`fast_equilibria`, the route
`analysis.equilibria` takes) on the salient machine at negative speed with a resistance
and an inductance error: the behaviour of the slow test
`test_fast_route_agrees_with_generic_route_at_one_point` (the generic root search
compiles for minutes), checked here by other routes at the same operating point, and at
the mirrored positive speed.

Against what:

- the equilibrium angles: the roots of the condition written out from the estimator's
  steady state (the back-EMF the mismatched model estimates lies on the estimated q axis
  with the sign of the speed), w psi_ext(x) sin x = dR i_d - dL w i_q with
  psi_ext(x) = psi_f + (L_d - L_q)(i_d cos x - i_q sin x) and s e_q > 0, found here by a
  dense sign-change scan and bisection in NumPy; theta = -x;
- that each reported state is an equilibrium: `error_rhs` vanishes there (the
  definition the generic route solves), and does not at a nearby angle;
- the Jacobian against central differences of `error_rhs`, and stability against the
  eigenvalues of that finite-difference Jacobian (NumPy), not Routh-Hurwitz.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax import analysis
from pmsmjax.analysis import _generic
from pmsmjax.observers import OperatingPoint


DRIVE = pj.preset("stumper_mt5")
PLANT = DRIVE.three_phase_motor
MODEL = pj.PMSMParams(R_s=1.5, L_d=4.0e-3, L_q=9.0e-3, psi_f=0.25, n_p=3.0)
OBS = pj.ParallelModelObserver.from_drive(DRIVE).with_motor(MODEL)
I0 = (0.3, -3.0)


def _roots_numpy(w, i0):
    """Equilibrium angles theta = -x of the steady-state condition (module docstring)."""
    R, Ld, Lq, psi = (float(getattr(PLANT, n)) for n in ("R_s", "L_d", "L_q", "psi_f"))
    dR, dL = float(MODEL.R_s) - R, float(MODEL.L_q) - Lq
    i_d, i_q = i0
    num = dR * i_d - dL * w * i_q

    def psi_ext(x):
        return psi + (Ld - Lq) * (i_d * np.cos(x) - i_q * np.sin(x))

    def h(x):
        return w * psi_ext(x) * np.sin(x) - num

    xs = np.linspace(-math.pi, math.pi, 20001)
    hs = h(xs)
    roots = []
    for k in np.nonzero(np.sign(hs[:-1]) != np.sign(hs[1:]))[0]:
        a, b = xs[k], xs[k + 1]
        for _ in range(200):
            c = 0.5 * (a + b)
            if np.sign(h(c)) == np.sign(h(a)):
                a = c
            else:
                b = c
        x = 0.5 * (a + b)
        e_q = w * psi_ext(x) * np.cos(x) - dR * i_q - dL * w * i_d
        if np.sign(w) * e_q > 0:
            roots.append(-x)
    return np.sort(np.angle(np.exp(1j * np.asarray(roots))))


#: the error dynamics, compiled once (op by op, each of their small operations would
#: compile on its own)
_rhs = jax.jit(lambda x, op: OBS.error_rhs(x, op, PLANT))


def _fd_jacobian(x, op, scale):
    n = x.shape[0]
    J = np.zeros((n, n))
    for j in range(n):
        hj = 1e-6 * float(scale[j])
        e = jnp.zeros(n).at[j].set(hj)
        J[:, j] = (np.asarray(_rhs(x + e, op)) - np.asarray(_rhs(x - e, op))) / (2 * hj)
    return J


@pytest.mark.parametrize("sign", [-1.0, 1.0])
def test_closed_form_equilibria_against_independent_routes(sign):
    w = sign * 0.2 * float(DRIVE.w_rated)
    i0 = jnp.array(I0)
    eq = analysis.equilibria(OBS, PLANT, w, i0)
    op = OperatingPoint(w, i0)
    # `analysis.equilibria` took the family's route (compiled as one program)
    own = _generic._fast_equilibria(OBS, PLANT, op)
    assert own is not None
    np.testing.assert_array_equal(np.asarray(eq.theta), np.asarray(own.theta))
    assert int(eq.status) == 0
    n = int(eq.n)
    ref = _roots_numpy(w, I0)
    assert n == len(ref) >= 1
    # bisection to the last bit; the closed form's Newton steps to ~1e-12 rad
    np.testing.assert_allclose(np.asarray(eq.theta)[:n], ref, rtol=0, atol=1e-9)
    # the mismatch moves the equilibrium away from zero (the check is not about zero)
    assert np.min(np.abs(ref)) > math.radians(0.5)

    scale = np.asarray(OBS.error_scale(op, PLANT))
    rate = abs(w)
    for j in range(n):
        x = jnp.asarray(np.asarray(eq.x)[j])
        f = np.asarray(_rhs(x, op)) / (scale * rate)
        assert np.abs(f).max() < 1e-9
        # one degree away from it the angle error is not at rest
        f_off = np.asarray(_rhs(x.at[2].add(math.radians(1.0)), op))
        assert np.abs(f_off / (scale * rate)).max() > 1e-3
        # Jacobian against central differences (relative step 1e-6: error ~1e-10 of the
        # largest entry, far below the 1e-6 allowed)
        J_fd = _fd_jacobian(x, op, scale)
        J = np.asarray(eq.jacobian)[j]
        np.testing.assert_allclose(J, J_fd, rtol=0, atol=1e-6 * np.abs(J_fd).max())
        # stability from the eigenvalues of the finite-difference Jacobian
        re = np.linalg.eigvals(J_fd).real
        assert np.abs(re).min() > 1e-6 * rate  # not marginal: the sign decides
        assert bool(np.asarray(eq.stable)[j]) == bool(np.all(re < 0))


def test_a_new_operating_point_reuses_the_compiled_route():
    """`analysis.equilibria` runs the family's closed form as one compiled program (op by
    op it dispatched about 180 single operations, each compiled on first use): a
    second operating point (other values, same shapes) reuses that program."""
    w_r = float(DRIVE.w_rated)
    first = analysis.equilibria(OBS, PLANT, 0.3 * w_r, jnp.array(I0))
    n = _generic._fast_equilibria._cached._cache_size()
    assert n >= 1
    eq = analysis.equilibria(OBS, PLANT, -0.4 * w_r, jnp.array((0.1, 2.0)))
    assert _generic._fast_equilibria._cached._cache_size() == n
    assert int(eq.status) == int(first.status) == 0
    assert not np.allclose(np.asarray(eq.theta)[:int(eq.n)],
                           np.asarray(first.theta)[:int(eq.n)])
