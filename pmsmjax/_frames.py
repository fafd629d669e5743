r"""Coordinate transforms for space vectors.

Space vectors are real arrays whose last axis has length 2 (`[x, y]`); leading axes
broadcast. Transforms are amplitude invariant: a balanced three-phase set of peak value
$A$ maps to a vector of length $A$.

- `J = [[0, -1], [1, 0]]`, and `rotate(x, theta)` multiplies by
  $e^{\theta J} = \cos\theta\, I + \sin\theta\, J$ (counter-clockwise rotation).
- `park(x_ab, theta) = rotate(x_ab, -theta)`, `inv_park(x_dq, theta) = rotate(x_dq, theta)`.
- `wrap_angle` maps to $(-\pi, \pi]$; `angle_error(theta, theta_hat)` is
  `wrap(theta - theta_hat)` (true minus estimate).
- `back_emf_angle(e, sigma)`: the rotor's d-axis angle read off a back-EMF vector,
  $\mathrm{atan2}(-\sigma e_\alpha, \sigma e_\beta)$.
- `vsd` / `inv_vsd`: vector-space decomposition of a dual three-phase machine with sets
  `a1 b1 c1` at 0, 120, 240 deg and `a2 b2 c2` shifted by `gamma` (default 30 deg).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np


J = np.array([[0.0, -1.0], [1.0, 0.0]])

_CLARKE = (2.0 / 3.0) * np.array(
    [[1.0, -0.5, -0.5], [0.0, math.sqrt(3) / 2, -math.sqrt(3) / 2]]
)
_INV_CLARKE = np.array([[1.0, 0.0], [-0.5, math.sqrt(3) / 2], [-0.5, -math.sqrt(3) / 2]])


def _vec(x, y):
    return jnp.stack([x, y], axis=-1)


def jmul(x):
    """Multiply the 2-vector(s) `x` by `J` (rotate by +90 deg)."""
    x = jnp.asarray(x)
    return _vec(-x[..., 1], x[..., 0])


@jax.custom_jvp
def cos_sin(theta):
    """`(cos(theta), sin(theta))`, each evaluated once per element (used on hot paths).

    XLA's CPU fusion counts `sin`/`cos` as cheap and recomputes them inside every fused
    consumer of their result, and once per row of a stacked result: a rotation's two
    components each computed both. Dividing by a runtime one (`theta - theta + 1`, exactly 1
    for finite `theta`; NaN otherwise, where the results are NaN anyway) is an identity
    that XLA counts as expensive, so it computes each value once and reuses it. The JVP
    is written out so that derivatives reuse the same two values.
    """
    one = theta - theta + 1.0
    return jnp.cos(theta) / one, jnp.sin(theta) / one


@cos_sin.defjvp
def _cos_sin_jvp(primals, tangents):
    (theta,), (dtheta,) = primals, tangents
    c, s = cos_sin(theta)
    return (c, s), (-s * dtheta, c * dtheta)


def _rotate_cs(x, c, s):
    """exp(theta J) x from c = cos(theta), s = sin(theta)."""
    return _vec(c * x[..., 0] - s * x[..., 1], s * x[..., 0] + c * x[..., 1])


# `rotate`, `park` and `wrap_angle` are jitted: called outside a trace (on a trajectory's
# arrays, by metrics and replay), each of their operations would otherwise compile a
# program of its own for every new shape; inside a trace the call is inlined.
@jax.jit
def rotate(x, theta):
    """Rotate 2-vector(s) `x` by angle `theta` (rad): exp(theta J) x."""
    return _rotate_cs(jnp.asarray(x), *cos_sin(theta))


def rot_matrix(theta):
    """The 2x2 matrix exp(theta J) (for scalar `theta`)."""
    c, s = jnp.cos(theta), jnp.sin(theta)
    return jnp.array([[c, -s], [s, c]])


@jax.jit
def park(x_ab, theta):
    """Stationary -> rotating frame at angle `theta` (rad): `rotate(x_ab, -theta)`, with the
    cosine and sine of `theta` itself (shared with `inv_park` at the same angle)."""
    c, s = cos_sin(theta)
    return _rotate_cs(jnp.asarray(x_ab), c, -s)


def inv_park(x_dq, theta):
    """Rotating frame at angle `theta` (rad) -> stationary."""
    return rotate(x_dq, theta)


def clarke(x_abc):
    """Three phase quantities (last axis 3) -> alpha-beta (last axis 2), amplitude invariant.

    The zero-sequence component is discarded (use `clarke0` to keep it).
    """
    return jnp.asarray(x_abc) @ jnp.asarray(_CLARKE.T)


def clarke0(x_abc):
    """Zero-sequence component (x_a + x_b + x_c) / 3."""
    return jnp.mean(jnp.asarray(x_abc), axis=-1)


def inv_clarke(x_ab, x_0=0.0):
    """alpha-beta (last axis 2) and optional zero sequence -> phase quantities (last axis 3)."""
    return jnp.asarray(x_ab) @ jnp.asarray(_INV_CLARKE.T) + jnp.asarray(x_0)[..., None]


@jax.jit
def wrap_angle(theta):
    """Wrap angle(s) to (-pi, pi]."""
    w = jnp.remainder(theta + jnp.pi, 2 * jnp.pi) - jnp.pi
    # remainder gives [-pi, pi); move -pi to +pi so the interval is (-pi, pi].
    return jnp.where(w <= -jnp.pi, w + 2 * jnp.pi, w)


def rotation_between(a, b):
    """The angle (rad, in (-pi, pi]) by which the 2-vector(s) `a` turn to reach `b` (last
    axis): atan2 of their cross and dot products. Where both vanish (a zero vector) it is
    0, with a finite gradient (atan2(0, 0)'s is not)."""
    cross = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    dot = a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]
    return jnp.arctan2(cross, jnp.where((cross == 0) & (dot == 0), 1.0, dot))


def back_emf_angle(e, sigma=1.0):
    r"""The angle (rad, in $[-\pi, \pi]$) of the rotor's d axis read off its back-EMF `e`
    (V, last axis 2; in any frame, the angle is then relative to that frame's first
    axis): $\mathrm{atan2}(-\sigma e_\alpha, \sigma e_\beta)$.

    The (extended) back-EMF $\omega\psi_{ex}[-\sin\theta, \cos\theta]$ lies on the q
    axis, 90 deg ahead of the d axis in the direction of rotation, so its direction gives
    the angle once the sign of the speed is known: `sigma` = $\mathrm{sign}\,\omega$
    (+1 or -1; broadcasts). With the wrong sign the angle is off by $\pi$."""
    return jnp.arctan2(-sigma * e[..., 0], sigma * e[..., 1])


def angle_error(theta, theta_hat):
    """Estimation error true minus estimate, wrapped to (-pi, pi] (rad)."""
    return wrap_angle(theta - theta_hat)


def vsd_matrix(gamma: float = math.pi / 6) -> np.ndarray:
    r"""The 6x6 amplitude-invariant vector-space-decomposition matrix.

    Rows: alpha, beta, x, y, o1, o2. Columns: phases `a1 b1 c1 a2 b2 c2`, where set 1 sits
    at electrical angles 0, 2pi/3, 4pi/3 and set 2 at gamma + (0, 2pi/3, 4pi/3).
    A balanced positive-sequence fundamental of amplitude A in both sets (set 2 lagging
    by `gamma` in time, as its winding is shifted by `gamma` in space) maps to an
    alpha-beta vector of length A and zero x-y; the 5th and 7th harmonics (k = 6m +- 1,
    m odd) map to x-y only; zero-sequence currents of each set map to o1, o2.
    """
    ang = np.array([0.0, 2 * np.pi / 3, 4 * np.pi / 3,
                     gamma, gamma + 2 * np.pi / 3, gamma + 4 * np.pi / 3])
    # x-y subspace: the plane the 5th harmonic occupies, i.e. angles multiplied by 5.
    T = np.empty((6, 6))
    T[0] = np.cos(ang)
    T[1] = np.sin(ang)
    T[2] = np.cos(5 * ang)
    T[3] = np.sin(5 * ang)
    T[4] = np.r_[np.ones(3), np.zeros(3)]
    T[5] = np.r_[np.zeros(3), np.ones(3)]
    return T / 3.0


def vsd(x_6):
    """Six phase quantities `a1 b1 c1 a2 b2 c2` (last axis 6) -> `(x_ab, x_xy, x_o)`.

    Uses the 30-degree `vsd_matrix`; see it for the mapping of harmonics.
    """
    y = jnp.asarray(x_6) @ jnp.asarray(vsd_matrix().T)
    return y[..., 0:2], y[..., 2:4], y[..., 4:6]


def inv_vsd(x_ab, x_xy, x_o=None):
    """Inverse of `vsd`: `(x_ab, x_xy, x_o)` -> six phase quantities (last axis 6)."""
    x_ab = jnp.asarray(x_ab)
    if x_o is None:
        x_o = jnp.zeros_like(x_ab)
    y = jnp.concatenate([x_ab, jnp.asarray(x_xy), jnp.asarray(x_o)], axis=-1)
    return y @ jnp.asarray(np.linalg.inv(vsd_matrix()).T)
