"""Loop carries batched from the start under `vmap`, and with a tangent under `jax.grad`
(`pmsmjax._sim._batching.batched_like`): the values stay what they were, and `vmap` of the
loop batches its body once instead of once per link of the chain by which the batched
input reaches the last carry (JAX's scan batching rule, counted by its calls of
`batch_jaxpr`); a gradient linearises it fewer times (`linearize_jaxpr`, `jvp_jaxpr`)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax._src.interpreters import ad, batching

import pmsmjax as pj
from pmsmjax._data import _replay
from pmsmjax._sim import _simulate
from pmsmjax._sim._batching import batched_like


def _trace_again(jitted):
    """Make the next call of the library's jitted function `jitted` (an `eqx.filter_jit`)
    trace again, by dropping its own compiled programs only: `jax.clear_caches()` would
    drop every program the worker has compiled, which its later tests then compile
    again."""
    jitted._cached.clear_cache()


def _count_calls(monkeypatch, module, *names):
    """A one-element list that counts the calls of `module.<name>` for each name (JAX's
    passes over a loop body, inside the test)."""
    count = [0]

    def counting(inner):
        def counted(*args, **kwargs):
            count[0] += 1
            return inner(*args, **kwargs)
        return counted

    for name in names:
        monkeypatch.setattr(module, name, counting(getattr(module, name)))
    return count


@pytest.fixture
def passes(monkeypatch):
    """Counts the body batchings of every scan batching rule run inside the test."""
    return _count_calls(monkeypatch, batching, "batch_jaxpr")


def _chain(p, use):
    """A loop whose batched parameter `p` reaches carry k only after k steps (a chain of
    five carries), with an integer and a boolean carry and a None leaf."""
    c0 = dict(x=[jnp.zeros(()) for _ in range(5)], n=jnp.int32(0), ok=jnp.array(True),
              none=None)
    if use:
        c0 = batched_like(c0, p, None, 3)  # None and a Python int are not arrays: skipped

    def body(c, k):
        x = c["x"]
        x = [p * k + 0.5 * x[0]] + [a + 0.5 * b for a, b in zip(x[:-1], x[1:])]
        return dict(x=x, n=c["n"] + 1, ok=c["ok"] & (x[-1] < 1e9), none=None), x[-1]

    return jax.lax.scan(body, c0, jnp.arange(12.0))


def test_values_are_unchanged_and_the_body_is_batched_once(passes):
    ps = jnp.linspace(-1.0, 2.0, 3)
    counts = {}
    for use in (False, True):
        passes[0] = 0
        jax.make_jaxpr(jax.vmap(lambda p: _chain(p, use)))(ps)
        counts[use] = passes[0]
    assert counts[True] == 1  # one pass over the body
    assert counts[False] == 6  # one per link of the chain, and one to confirm
    for p in (ps, ps[0]):  # batched and not: the same numbers bit for bit
        f = (jax.vmap if p.ndim else (lambda g: g))
        a = jax.jit(f(lambda q: _chain(q, False)))(p)
        b = jax.jit(f(lambda q: _chain(q, True)))(p)
        for u, v in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
            assert u.dtype == v.dtype
            np.testing.assert_array_equal(np.asarray(u), np.asarray(v))
    # no array to follow: the carry is returned as it is
    c = dict(x=jnp.ones(2))
    assert batched_like(c, None, 1.0) is c


def test_vmapped_simulation_batches_its_step_fewer_times_with_the_same_numbers(
        passes, monkeypatch):
    """`simulate` under `vmap` (loads, noise keys): the same trajectories whether its
    carries start batched or not, with fewer batchings of the step."""
    drive = pj.preset("zhang750")
    foc = pj.FOC.from_drive(drive)
    obs = pj.observers.make_observer("eso", drive)

    def one(load, key):
        sc = pj.Scenario(t_end=0.01, w_m_ref=pj.Profile.constant(100.0),
                         tau_L=pj.Profile.constant(load))
        tr = pj.simulate(drive, foc, obs, sc, sensing=pj.Sensing(noise_std=0.01), key=key,
                         save_every=4, throw=False)
        return tr.theta_err, tr.w_hat, tr.i_dq

    loads = jnp.linspace(0.0, 1.0, 3)
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    out, counts = {}, {}
    for use in (True, False):
        if not use:
            monkeypatch.setattr(_simulate, "batched_like", lambda c, *deps: c)
        _trace_again(_simulate._simulate)  # its program is cached by shape
        passes[0] = 0
        f = jax.jit(jax.vmap(one))
        f.lower(loads, keys)
        counts[use] = passes[0]
        out[use] = f(loads, keys)
    assert counts[True] < counts[False]
    for u, v in zip(out[True], out[False]):
        np.testing.assert_array_equal(np.asarray(u), np.asarray(v))


def test_replay_gradient_linearises_its_step_fewer_times_with_the_same_gradient(
        monkeypatch):
    """`jax.grad` through `replay_estimates` with respect to a gain: the scan's
    linearisation fixpoint (which carries have a nonzero tangent; JAX's
    `linearize_jaxpr`, or `jvp_jaxpr` where the scan is differentiated by its JVP rule)
    linearises the step fewer times when the initial state follows the observer
    (`batched_like`) than when it starts from constants; the gradient is the same to
    round-off."""
    drive = pj.preset("zhang750")
    n = 200
    th = 300.0 * 1e-4 * np.arange(n)
    i_ab = 2.0 * np.stack([-np.sin(th), np.cos(th)], 1)
    u_ab = 20.0 * np.stack([-np.sin(th + 0.1), np.cos(th + 0.1)], 1)
    obs = pj.observers.make_observer("c-leso", drive)

    def loss(g):
        est = pj.replay_estimates(obs.with_design(w0=g), u_ab=u_ab, i_ab=i_ab, T_s=1e-4,
                                  theta0=0.3, w0=300.0)
        return jnp.sum(est.theta_hat)

    count = _count_calls(monkeypatch, ad, "jvp_jaxpr", "linearize_jaxpr")
    grads, counts = {}, {}
    for use in (True, False):
        if not use:
            monkeypatch.setattr(_replay, "batched_like", lambda c, *deps: c)
        _trace_again(_replay._scan)
        count[0] = 0
        grads[use] = float(jax.grad(loss)(float(obs.w0)))
        counts[use] = count[0]
    assert counts[True] < counts[False]
    assert grads[True] == pytest.approx(grads[False], rel=1e-12)
