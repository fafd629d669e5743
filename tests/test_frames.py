"""Coordinate transforms: Clarke/Park, rotations, angle wrapping and the six-phase VSD.

Every expected value is computed here from its definition (trigonometry written out in
numpy), never taken from the library.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmsmjax as pj


RNG = np.random.default_rng(1234)
J_REF = np.array([[0.0, -1.0], [1.0, 0.0]])
ANG3 = np.array([0.0, 2 * np.pi / 3, 4 * np.pi / 3])
# Six-phase winding angles a1 b1 c1 a2 b2 c2 (set 2 shifted by 30 deg in space).
ANG6 = np.deg2rad([0.0, 120.0, 240.0, 30.0, 150.0, 270.0])


def rot(theta):
    return np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])


# --------------------------------------------------------------------------------------
# Clarke / Park
# --------------------------------------------------------------------------------------

def test_clarke_amplitude_invariance():
    # Balanced set of peak A at phase angle phi: x_k = A cos(phi - 2 pi k / 3) -> the
    # amplitude-invariant vector is A [cos phi, sin phi] (length A, angle phi).
    A = 7.3
    phi = np.linspace(-4.0, 9.0, 57)
    x_abc = A * np.cos(phi[:, None] - ANG3[None, :])
    x_ab = np.asarray(pj.clarke(x_abc))
    np.testing.assert_allclose(x_ab, A * np.stack([np.cos(phi), np.sin(phi)], -1),
                               rtol=0, atol=1e-13 * A)
    np.testing.assert_allclose(np.linalg.norm(x_ab, axis=-1), A, rtol=1e-14)
    # A balanced set has no zero sequence.
    np.testing.assert_allclose(np.asarray(pj.clarke0(x_abc)), 0.0, atol=1e-13 * A)


def test_clarke_round_trip():
    x_abc = RNG.normal(size=(20, 3))
    x0 = x_abc.mean(-1)
    np.testing.assert_allclose(np.asarray(pj.clarke0(x_abc)), x0, rtol=1e-14)
    back = np.asarray(pj.inv_clarke(pj.clarke(x_abc), pj.clarke0(x_abc)))
    np.testing.assert_allclose(back, x_abc, atol=1e-14)
    # Without zero sequence the round trip returns the zero-sequence-free part.
    back0 = np.asarray(pj.inv_clarke(pj.clarke(x_abc)))
    np.testing.assert_allclose(back0, x_abc - x0[:, None], atol=1e-14)
    # ... and alpha-beta -> abc -> alpha-beta is the identity.
    x_ab = RNG.normal(size=(20, 2))
    np.testing.assert_allclose(np.asarray(pj.clarke(pj.inv_clarke(x_ab))), x_ab, atol=1e-14)


def test_inv_clarke_phase_values():
    # The vector A [cos phi, sin phi] is the balanced set A cos(phi - a_k).
    A, phi = 2.5, 0.7
    x_abc = np.asarray(pj.inv_clarke(A * np.array([np.cos(phi), np.sin(phi)])))
    np.testing.assert_allclose(x_abc, A * np.cos(phi - ANG3), atol=1e-14)


def test_park_round_trip_and_definition():
    x = RNG.normal(size=(30, 2))
    th = RNG.uniform(-10, 10, size=30)
    x_dq = np.asarray(pj.park(x, th))
    # park = rotation by -theta
    ref = np.einsum("kij,kj->ki", np.stack([rot(-t) for t in th]), x)
    np.testing.assert_allclose(x_dq, ref, atol=1e-14)
    np.testing.assert_allclose(np.asarray(pj.inv_park(x_dq, th)), x, atol=1e-13)
    np.testing.assert_allclose(np.asarray(pj.park(pj.inv_park(x, th), th)), x, atol=1e-13)
    # A vector rotating with theta is constant in the rotating frame.
    A, phi = 3.0, 0.4
    v_ab = A * np.stack([np.cos(th + phi), np.sin(th + phi)], -1)
    np.testing.assert_allclose(np.asarray(pj.park(v_ab, th)),
                               np.broadcast_to([A * np.cos(phi), A * np.sin(phi)], (30, 2)),
                               atol=1e-13)


def test_rotate_equals_rot_matrix():
    np.testing.assert_array_equal(np.asarray(pj.J), J_REF)
    for th in RNG.uniform(-7, 7, size=10):
        x = RNG.normal(size=2)
        R = np.asarray(pj.rot_matrix(th))
        np.testing.assert_allclose(R, rot(th), atol=1e-15)
        # exp(theta J) = cos(theta) I + sin(theta) J
        np.testing.assert_allclose(R, np.cos(th) * np.eye(2) + np.sin(th) * J_REF, atol=1e-15)
        np.testing.assert_allclose(np.asarray(pj.rotate(x, th)), R @ x, atol=1e-14)


def test_jmul():
    x = RNG.normal(size=(12, 2))
    np.testing.assert_array_equal(np.asarray(pj.jmul(x)), x @ J_REF.T)
    # J is a +90 degree rotation, J^2 = -I.
    np.testing.assert_allclose(np.asarray(pj.jmul(x)), np.asarray(pj.rotate(x, np.pi / 2)),
                               atol=1e-15)
    np.testing.assert_array_equal(np.asarray(pj.jmul(pj.jmul(x))), -x)


# --------------------------------------------------------------------------------------
# Angles
# --------------------------------------------------------------------------------------

def test_wrap_angle_interval():
    x = np.concatenate([RNG.uniform(-50, 50, 200), np.linspace(-20, 20, 101)])
    w = np.asarray(pj.wrap_angle(x))
    assert np.all(w > -np.pi) and np.all(w <= np.pi)
    # wrapped differs from the input by an integer number of turns
    k = (x - w) / (2 * np.pi)
    np.testing.assert_allclose(k, np.round(k), atol=1e-12)
    # inside (-pi, pi] nothing changes
    y = np.array([-3.0, -1.0, 0.0, 0.5, 3.1])
    np.testing.assert_allclose(np.asarray(pj.wrap_angle(y)), y, atol=1e-15)


@pytest.mark.parametrize("k", [0, 1, -1, 2, -3, 1000, -1001])
def test_wrap_angle_edges(k):
    # pi and -pi (and their odd multiples) map to +pi (the interval is (-pi, pi]).
    w = float(pj.wrap_angle(np.pi + 2 * np.pi * k))
    assert abs(w - np.pi) < 1e-9 * max(1, abs(k)) or abs(w + np.pi) < 1e-9 * max(1, abs(k))
    assert w > -np.pi
    # An exact multiple of 2 pi maps to 0, and pi/2 stays pi/2 after many turns.
    assert abs(float(pj.wrap_angle(2 * np.pi * k))) < 1e-12 * max(1, abs(k))
    np.testing.assert_allclose(float(pj.wrap_angle(0.5 * np.pi + 2 * np.pi * k)),
                               0.5 * np.pi, atol=1e-12 * max(1, abs(k)))


def test_wrap_angle_exact_pi():
    assert float(pj.wrap_angle(np.pi)) == pytest.approx(np.pi, abs=1e-15)
    assert float(pj.wrap_angle(-np.pi)) == pytest.approx(np.pi, abs=1e-15)
    assert float(pj.wrap_angle(3 * np.pi)) == pytest.approx(np.pi, abs=1e-14)
    assert float(pj.wrap_angle(-3 * np.pi)) == pytest.approx(np.pi, abs=1e-14)


def test_angle_error_sign():
    # True minus estimate: the estimate lags by 0.1 rad -> +0.1.
    assert float(pj.angle_error(1.0, 0.9)) == pytest.approx(0.1, abs=1e-14)
    assert float(pj.angle_error(0.9, 1.0)) == pytest.approx(-0.1, abs=1e-14)
    # Across the wrap point: true 3.1, estimate -3.1 -> 6.2 - 2 pi (negative, small).
    assert float(pj.angle_error(3.1, -3.1)) == pytest.approx(6.2 - 2 * np.pi, abs=1e-13)
    assert float(pj.angle_error(-3.1, 3.1)) == pytest.approx(2 * np.pi - 6.2, abs=1e-13)
    th, th_hat = RNG.uniform(-20, 20, 50), RNG.uniform(-20, 20, 50)
    e = np.asarray(pj.angle_error(th, th_hat))
    np.testing.assert_allclose(np.sin(e), np.sin(th - th_hat), atol=1e-12)
    np.testing.assert_allclose(np.cos(e), np.cos(th - th_hat), atol=1e-12)


# --------------------------------------------------------------------------------------
# Vector-space decomposition (dual three-phase)
# --------------------------------------------------------------------------------------

def test_vsd_matrix_invertible_and_round_trip():
    T = np.asarray(pj.vsd_matrix())
    assert T.shape == (6, 6)
    assert abs(np.linalg.det(T)) > 1e-3
    # The rows are orthogonal; each has squared norm 3/9: sum_k cos^2(a_k) = 3 over the
    # six phases for alpha, beta, x, y, and three ones for o1, o2 (all scaled by 1/3).
    G = T @ T.T
    np.testing.assert_allclose(G, np.eye(6) / 3, atol=1e-14)
    x6 = RNG.normal(size=(25, 6))
    x_ab, x_xy, x_o = pj.vsd(x6)
    np.testing.assert_allclose(np.asarray(pj.inv_vsd(x_ab, x_xy, x_o)), x6, atol=1e-13)
    np.testing.assert_allclose(np.concatenate([np.asarray(x_ab), np.asarray(x_xy),
                                               np.asarray(x_o)], -1), x6 @ T.T, atol=1e-14)


def _six_phase(order, A, wt, phase=0.0):
    """Phase k value A cos(order (wt - ang_k) + phase), shape (len(wt), 6)."""
    return A * np.cos(order * (wt[:, None] - ANG6[None, :]) + phase)


WT = np.linspace(0.0, 2 * np.pi, 73)


def _assert_rotating(v, A, rate, phase=0.0):
    """v(wt) == A [cos(rate wt + phase), sin(rate wt + phase)]."""
    ref = A * np.stack([np.cos(rate * WT + phase), np.sin(rate * WT + phase)], -1)
    np.testing.assert_allclose(np.asarray(v), ref, atol=1e-13 * A)


def test_vsd_fundamental():
    A = 4.2
    x_ab, x_xy, x_o = pj.vsd(_six_phase(1, A, WT))
    # sum_k cos(a_k) cos(wt - a_k) = 3 cos(wt) over six phases; / 3 -> A cos(wt).
    _assert_rotating(x_ab, A, +1)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(x_ab), axis=-1), A, rtol=1e-13)
    np.testing.assert_allclose(np.asarray(x_xy), 0.0, atol=1e-13 * A)
    np.testing.assert_allclose(np.asarray(x_o), 0.0, atol=1e-13 * A)


@pytest.mark.parametrize(
    "order, rate",
    # x-row cos(5a) times cos(h wt - h a) = 1/2[cos(h wt - (h-5) a) + cos(h wt - (h+5) a)];
    # a six-phase sum of cos(X - m a_k) is 6 cos X if m = 0 (mod 12) and 0 otherwise.
    # h = 5: the (h-5) term survives: x = A cos 5wt, y = +A sin 5wt  -> rotates at +5w.
    # h = 7: the (h+5) term survives: x = A cos 7wt, y = -A sin 7wt  -> rotates at -7w.
    [(5, +5), (7, -7)],
)
def test_vsd_5th_7th_map_to_xy(order, rate):
    A = 0.9
    x_ab, x_xy, x_o = pj.vsd(_six_phase(order, A, WT))
    _assert_rotating(x_xy, A, rate)
    np.testing.assert_allclose(np.asarray(x_ab), 0.0, atol=1e-13)
    np.testing.assert_allclose(np.asarray(x_o), 0.0, atol=1e-13)
    # with a phase offset the x-y vector's angle carries it with the sign of the rotation
    x_ab, x_xy, _ = pj.vsd(_six_phase(order, A, WT, phase=0.3))
    _assert_rotating(x_xy, A, rate, phase=0.3 * np.sign(rate))


@pytest.mark.parametrize(
    "order, rate",
    # alpha row cos(a) cos(h wt - h a): m = h -+ 1 must be 0 mod 12.
    # h = 11: m = h + 1 = 12 -> alpha = A cos 11wt, beta = -A sin 11wt (rotates -11w);
    # h = 13: m = h - 1 = 12 -> rotates +13w.
    [(11, -11), (13, +13)],
)
def test_vsd_11th_13th_stay_in_alpha_beta(order, rate):
    A = 0.6
    x_ab, x_xy, x_o = pj.vsd(_six_phase(order, A, WT))
    _assert_rotating(x_ab, A, rate)
    np.testing.assert_allclose(np.asarray(x_xy), 0.0, atol=1e-13)
    np.testing.assert_allclose(np.asarray(x_o), 0.0, atol=1e-13)


def test_vsd_zero_sequence():
    z1, z2 = 1.7, -0.4
    x6 = np.r_[np.full(3, z1), np.full(3, z2)]
    x_ab, x_xy, x_o = pj.vsd(x6)
    np.testing.assert_allclose(np.asarray(x_o), [z1, z2], atol=1e-14)
    np.testing.assert_allclose(np.asarray(x_ab), 0.0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(x_xy), 0.0, atol=1e-14)
    # The triplen (3rd) harmonic of each set is zero sequence per set.
    x6 = _six_phase(3, 1.0, WT)
    _, _, x_o = pj.vsd(x6)
    np.testing.assert_allclose(np.asarray(x_o),
                               np.stack([np.cos(3 * WT), np.cos(3 * (WT - math.pi / 6))], -1),
                               atol=1e-13)


def test_inv_vsd_builds_balanced_sets():
    # inv_vsd of an alpha-beta vector A[cos phi, sin phi] gives A cos(phi - ang_k).
    A, phi = 3.3, -1.1
    x6 = np.asarray(pj.inv_vsd(A * np.array([np.cos(phi), np.sin(phi)]), np.zeros(2)))
    np.testing.assert_allclose(x6, A * np.cos(phi - ANG6), atol=1e-13)


def test_rotation_between_is_the_angle_of_the_complex_quotient():
    """Against complex arithmetic: the turn from a to b is arg(b / a); zero vectors give
    0 with a finite gradient."""
    from pmsmjax._frames import rotation_between

    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(2, 500, 2))
    ref = np.angle((b[:, 0] + 1j * b[:, 1]) / (a[:, 0] + 1j * a[:, 1]))
    np.testing.assert_allclose(np.asarray(rotation_between(jnp.asarray(a), jnp.asarray(b))),
                               ref, rtol=1e-13, atol=1e-14)
    z = jnp.zeros(2)
    assert float(rotation_between(z, jnp.array([1.0, 2.0]))) == 0.0
    g = jax.grad(lambda x: rotation_between(x, z))(z)
    assert np.all(np.isfinite(np.asarray(g)))


# --------------------------------------------------------------------------------------
# Each cosine and sine evaluated once (XLA recomputes them per fused consumer otherwise)
# --------------------------------------------------------------------------------------

def _trig_counts(fn, *args):
    """Sine and cosine operations in the optimised program of `jit(fn)` (a value that XLA
    recomputes in several fused loops counts once per loop)."""
    import re

    text = jax.jit(fn).lower(*args).compile().as_text()
    return (len(re.findall(r"\bsine\(", text)), len(re.findall(r"\bcosine\(", text)))


def test_rotations_evaluate_each_sine_and_cosine_once():
    x = jnp.asarray(RNG.normal(size=(64, 2)))
    th = jnp.asarray(RNG.uniform(-4, 4, 64))
    # park and inv_park at one angle share one cosine and one sine (before: park took
    # the pair of the negated angle)
    assert _trig_counts(jax.vmap(pj.rotate), x, th) == (1, 1)
    assert _trig_counts(jax.vmap(lambda v, t: pj.inv_park(pj.park(v, t) * 2.0, t)),
                        x, th) == (1, 1)
    # zhang2022's ESO step: the estimator-frame pair, the pair at theta + w_f T_s / 2 and
    # the sine of sinc(w_f T_s / 2) (29 evaluations per step of the closed loop before,
    # where 17 are needed)
    drive = pj.preset("zhang750")
    obs = pj.observers.make_observer("eso", drive)
    state = jax.vmap(lambda t: obs.init(theta0=t, w0=100.0))(th)
    meas = pj.observers.Measurement(i_ab=x, u_ab=x * 3.0, theta=th, w_m=th)
    assert _trig_counts(jax.vmap(lambda s, m: obs.step(s, m, 1e-4)), state, meas) == (3, 2)
    # li-fa-leso's LESOs: the pair of the hold's half angle and the pair at the PLL's
    # predicted angle (shared with the model's d current), one sine of them in two fused
    # loops (five pairs before)
    dtp = pj.preset("li_dtp")
    for name in ("c-leso", "gi-leso", "fa-leso"):
        obs = pj.observers.make_observer(name, dtp)
        state = jax.vmap(lambda t: obs.init(theta0=t, w0=100.0))(th)
        assert _trig_counts(jax.vmap(lambda s, m: obs.step(s, m, 1e-4)), state, meas) == (
            3, 2), name


def test_rotation_derivatives_against_finite_differences():
    x = jnp.array([0.7, -1.3])
    for fn in (pj.rotate, pj.park, pj.inv_park):
        for t in (-2.0, 0.3, 3.0):
            g = jax.jacfwd(fn, argnums=1)(x, t)
            gr = jax.jacrev(fn, argnums=1)(x, t)
            h = 1e-6
            fd = (np.asarray(fn(x, t + h)) - np.asarray(fn(x, t - h))) / (2 * h)
            np.testing.assert_allclose(g, fd, atol=1e-9)
            np.testing.assert_allclose(gr, fd, atol=1e-9)
            # second derivative: the rotation's d2/dtheta2 = -rotation
            g2 = jax.jacfwd(jax.jacrev(fn, argnums=1), argnums=1)(x, t)
            np.testing.assert_allclose(g2, -np.asarray(fn(x, t)), atol=1e-12)
