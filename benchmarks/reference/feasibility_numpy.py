"""zhang2022's feasibility classification (Fig. 1) written with NumPy, independent of
pmsmjax: every equilibrium of the ESO error dynamics (11) from the quartic (36), the
stability of each from the Jacobian (37), for the matched ESO with fixed-ratio gains
(zeta2 = 1, w2 = `W2`). `numpy_point` is the route point by point as one would write it
with NumPy (`numpy.roots`, `numpy.linalg.eigvals`); `numpy_batched` the same vectorised
over points (batched companion matrices and Jacobians). Both return `(status,
n_nonzero)`: 1 if a nonzero equilibrium is stable (infeasible), and the number of nonzero
equilibria. `benchmarks.throughput.feasibility` times them against pmsmjax and checks
that every point agrees.
"""

from __future__ import annotations

import math

import numpy as np


W2 = 2 * math.pi * 50.0  # the speed loop's bandwidth (rad/s)


J2 = np.array([[0.0, -1.0], [1.0, 0.0]])


def _gains(w0, i_d, i_q, zeta1, ratio, L_d, L_q, psi_f):
    psi = np.array([(L_d - L_q) * i_d + psi_f, -(L_d - L_q) * i_q])
    n2 = psi @ psi
    w1 = ratio * abs(w0)
    c = w1 ** 2 / w0 - w0
    G1 = (2 * zeta1 * w1 * np.outer(psi, psi) + c * np.outer(J2 @ psi, psi)) / n2
    row = np.array([psi[1], -psi[0]]) / n2
    return psi, G1, 2 * W2 * row, W2 ** 2 * row  # zeta2 = 1


def _p35(w0, i_d, i_q, psi, G1, L_d, L_q, psi_f):
    beta = -psi[1] / psi[0]
    g1, g2 = G1[0, 0], G1[1, 0]
    dL, b2 = 0.5 * (L_d - L_q), beta ** 2 + 1
    p1 = dL * ((beta * i_d - i_q) * w0 + b2 * (g1 * i_d - g2 * i_q))
    p2 = dL * ((beta * i_q + i_d) * w0 + b2 * (g2 * i_d + g1 * i_q))
    p3 = psi_f * (beta * w0 + b2 * g1)
    p4 = psi_f * (w0 + b2 * g2)
    return p1, p2, p3, p4, -p1 - p3


def _rot(t):
    return np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])


def numpy_point(w0, i_d, i_q, zeta1, ratio, L_d, L_q, psi_f):
    """(status, n_nonzero) of one design: (35), numpy.roots of (36), (37), eigvals."""
    i0 = np.array([i_d, i_q])
    psi, G1, g2, g3 = _gains(w0, i_d, i_q, zeta1, ratio, L_d, L_q, psi_f)
    p1, p2, p3, p4, p5 = _p35(w0, i_d, i_q, psi, G1, L_d, L_q, psi_f)
    t = np.roots([p1 - p3 + p5, 2 * p4 - 4 * p2, 2 * p5 - 6 * p1, 4 * p2 + 2 * p4,
                  p1 + p3 + p5])
    L = np.diag([L_d, L_q])
    pf = np.array([psi_f, 0.0])
    M = w0 * J2 + G1
    n, stable = 0, False
    for root in t:
        if abs(root.imag) > 1e-7 * (1 + abs(root)):
            continue
        th = 2 * np.arctan(root.real)
        if abs(th) < 1e-6:
            continue
        n += 1
        R = _rot(th)
        e0 = L @ i0 + pf - R @ (L @ R.T @ i0 + pf)
        de0 = -(J2 @ R @ L @ R.T @ i0 - R @ L @ R.T @ J2 @ i0 + J2 @ R @ pf)
        x = -np.linalg.solve(M, G1 @ e0)
        e = e0 + x
        wf = w0 - g2 @ e + g2 @ e
        Jx = J2 @ x
        A = np.zeros((4, 4))
        A[:2, :2] = -wf * J2 - np.outer(Jx, g2) - G1
        A[:2, 2] = -Jx * (g2 @ de0) - G1 @ de0
        A[:2, 3] = Jx
        A[2] = [-g2[0], -g2[1], -g2 @ de0, 1.0]
        A[3] = [-g3[0], -g3[1], -g3 @ de0, 0.0]
        stable |= bool(np.max(np.linalg.eigvals(A).real) < 0)
    return int(stable), n


def numpy_batched(w0, i_d, i_q, zeta1, ratio, L_d, L_q, psi_f):
    """The same, vectorised over points; returns (status, n_nonzero) arrays."""
    nb = w0.shape[0]
    dL = L_d - L_q
    pd, pq = dL * i_d + psi_f, -dL * i_q
    n2 = pd ** 2 + pq ** 2
    w1 = ratio * np.abs(w0)
    c = w1 ** 2 / w0 - w0
    k = 2 * zeta1 * w1
    # G1 = (k psi psi^T + c (J psi) psi^T) / n2, J psi = (-pq, pd)
    G1 = np.empty((nb, 2, 2))
    G1[:, 0, 0] = (k * pd - c * pq) * pd / n2
    G1[:, 0, 1] = (k * pd - c * pq) * pq / n2
    G1[:, 1, 0] = (k * pq + c * pd) * pd / n2
    G1[:, 1, 1] = (k * pq + c * pd) * pq / n2
    row = np.stack([pq, -pd], -1) / n2[:, None]
    g2, g3 = 2 * W2 * row, W2 ** 2 * row
    beta = -pq / pd
    g1c, g2c = G1[:, 0, 0], G1[:, 1, 0]
    h, b2 = 0.5 * dL, beta ** 2 + 1
    p1 = h * ((beta * i_d - i_q) * w0 + b2 * (g1c * i_d - g2c * i_q))
    p2 = h * ((beta * i_q + i_d) * w0 + b2 * (g2c * i_d + g1c * i_q))
    p3 = psi_f * (beta * w0 + b2 * g1c)
    p4 = psi_f * (w0 + b2 * g2c)
    p5 = -p1 - p3
    coef = np.stack([p1 - p3 + p5, 2 * p4 - 4 * p2, 2 * p5 - 6 * p1, 4 * p2 + 2 * p4,
                     p1 + p3 + p5], -1)
    comp = np.zeros((nb, 4, 4))  # companion matrices of the quartic
    comp[:, 0, :] = -coef[:, 1:] / coef[:, :1]
    comp[:, 1, 0] = comp[:, 2, 1] = comp[:, 3, 2] = 1.0
    t = np.linalg.eigvals(comp)  # (nb, 4)
    real = np.abs(t.imag) <= 1e-7 * (1 + np.abs(t))
    th = 2 * np.arctan(t.real)
    ok = real & (np.abs(th) >= 1e-6)
    # equilibrium states and Jacobians for all 4 candidate roots at once
    ct, st = np.cos(th), np.sin(th)
    c2, s2 = np.cos(2 * th), np.sin(2 * th)
    hi = 0.5 * dL
    Id, Iq = i_d[:, None], i_q[:, None]
    e0 = np.stack([hi * (Id - c2 * Id - s2 * Iq) + psi_f * (1 - ct),
                   hi * (-Iq - s2 * Id + c2 * Iq) - psi_f * st], -1)
    de0 = np.stack([hi * (2 * s2 * Id - 2 * c2 * Iq) + psi_f * st,
                    hi * (-2 * c2 * Id - 2 * s2 * Iq) - psi_f * ct], -1)
    M = G1 + w0[:, None, None] * J2
    G1e = np.einsum("bij,bkj->bki", G1, e0)
    x = -np.linalg.solve(M[:, None], G1e[..., None])[..., 0]
    Jx = np.stack([-x[..., 1], x[..., 0]], -1)
    gd = np.einsum("bj,bkj->bk", g2, de0)
    hd = np.einsum("bj,bkj->bk", g3, de0)
    Gd = np.einsum("bij,bkj->bki", G1, de0)
    A = np.zeros((nb, 4, 4, 4))
    w = w0[:, None]
    A[..., 0, 0] = -Jx[..., 0] * g2[:, None, 0] - G1[:, None, 0, 0]
    A[..., 0, 1] = w - Jx[..., 0] * g2[:, None, 1] - G1[:, None, 0, 1]
    A[..., 1, 0] = -w - Jx[..., 1] * g2[:, None, 0] - G1[:, None, 1, 0]
    A[..., 1, 1] = -Jx[..., 1] * g2[:, None, 1] - G1[:, None, 1, 1]
    A[..., :2, 2] = -Jx * gd[..., None] - Gd
    A[..., :2, 3] = Jx
    A[..., 2, 0], A[..., 2, 1] = -g2[:, None, 0], -g2[:, None, 1]
    A[..., 2, 2], A[..., 2, 3] = -gd, 1.0
    A[..., 3, 0], A[..., 3, 1] = -g3[:, None, 0], -g3[:, None, 1]
    A[..., 3, 2] = -hd
    stab = np.max(np.linalg.eigvals(A).real, -1) < 0
    return np.any(stab & ok, -1).astype(np.int32), np.sum(ok, -1)
