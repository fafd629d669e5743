"""Batched LAPACK calls that could deadlock XLA's CPU thread pool (pmsmjax/_lapack_pool.py).

A batched LAPACK call with enough work blocks its pool thread until its chunks have run on
the same pool; two of them at once deadlock a 2-core machine. The Lyapunov certificate
had such a pair (the P and dP solves over the speed grid) and hung about one call in ten
on 2 cores (native stacks: both pool threads in jaxlib's `ParallelBatchMap`). These tests
check the HLO reader on small programs whose answer is known by construction, and that
the library's programs that use LAPACK have no such pair.
"""

import math

import jax
import jax.numpy as jnp
import pytest

import pmsmjax as pj
from pmsmjax import analysis, runtime
from pmsmjax.analysis import _lyapunov
from pmsmjax.observers import make_observer


def compiled(f, *args):
    return jax.jit(f).lower(*args).compile()


def mats(batch, n=16):
    a = jax.random.normal(jax.random.PRNGKey(batch), (batch, n, n)) + n * jnp.eye(n)
    return a, jnp.ones((batch, n, 1))


def pair_names(pairs):
    return sorted((a.routine, b.routine) for a, b in pairs)


def test_two_independent_batched_solves_are_a_pair_with_jaxlibs_work_estimate():
    a, x = mats(200)
    pairs = runtime.concurrent_lapack_calls(
        compiled(lambda a, b, x: (jnp.linalg.solve(a, x), jnp.linalg.solve(b, x)), a, a + 1, x))
    assert pair_names(pairs) == [("dgetrf", "dgetrf")]
    call = pairs[0][0]
    # getrf: m n min(m, n) FLOP per matrix (jaxlib), 200 matrices of 16 x 16
    assert (call.batch, call.shape, call.work) == (200, (16, 16), 200 * 16 ** 3)


@pytest.mark.parametrize("case", ["chained", "small", "unbatched"])
def test_programs_without_a_pair(case):
    a, x = mats(200)
    if case == "chained":  # the second matrix needs the first solve's result
        def f(a, b, x):
            y = jnp.linalg.solve(a, x)
            return jnp.linalg.solve(b + y * jnp.swapaxes(y, 1, 2), x)
        args = (a, a + 1, x)
    elif case == "small":  # 10 x 16^3 = 41k FLOP each: run inline, below jaxlib's 200k
        a, x = mats(10)
        f = lambda a, b, x: (jnp.linalg.solve(a, x), jnp.linalg.solve(b, x))  # noqa: E731
        args = (a, a + 1, x)
    else:  # lax.map: one matrix per call
        f = lambda a, b, x: jax.lax.map(  # noqa: E731
            lambda t: (jnp.linalg.solve(t[0], t[2]), jnp.linalg.solve(t[1], t[2])), (a, b, x))
        args = (a, a + 1, x)
    assert runtime.concurrent_lapack_calls(compiled(f, *args)) == []


def test_an_optimization_barrier_orders_nothing():
    """The second matrix passes through a barrier together with the first solve's result:
    XLA drops the barrier and factorises both matrices first, so it is still a pair."""
    a, x = mats(200)

    def f(a, b, x):
        y = jnp.linalg.solve(a, x)
        b2, _ = jax.lax.optimization_barrier((b, y))
        return y, jnp.linalg.solve(b2, x)

    pairs = runtime.concurrent_lapack_calls(compiled(f, a, a + 1, x))
    assert pair_names(pairs) == [("dgetrf", "dgetrf")]


HLO_TUPLE = """HloModule m, is_scheduled=true

ENTRY %main (p0: f64[200,16,16], p1: f64[200,16,16]) -> (f64[200,16,16], s32[200]) {
  %p0 = f64[200,16,16]{2,1,0} parameter(0)
  %p1 = f64[200,16,16]{2,1,0} parameter(1)
  %lu.1 = (f64[200,16,16]{2,1,0}, s32[200,16]{1,0}, s32[200]{0}) custom-call(%p0), \
custom_call_target="lapack_dgetrf_ffi", operand_layout_constraints={f64[200,16,16]{2,1,0}}
  %gte.1 = f64[200,16,16]{2,1,0} get-tuple-element(%lu.1), index=0
  %tuple.1 = (f64[200,16,16]{2,1,0}, f64[200,16,16]{2,1,0}) tuple(%p1, %gte.1)
  %opt-barrier.1 = (f64[200,16,16]{2,1,0}, f64[200,16,16]{2,1,0}) opt-barrier(%tuple.1)
  %gte.2 = f64[200,16,16]{2,1,0} get-tuple-element(%opt-barrier.1), index=INDEX
  %lu.2 = (f64[200,16,16]{2,1,0}, s32[200,16]{1,0}, s32[200]{0}) custom-call(%gte.2), \
custom_call_target="lapack_dgetrf_ffi", operand_layout_constraints={f64[200,16,16]{2,1,0}}
  %gte.3 = s32[200]{0} get-tuple-element(%lu.2), index=2
  ROOT %t = (f64[200,16,16]{2,1,0}, s32[200]{0}) tuple(%gte.1, %gte.3)
}
"""


@pytest.mark.parametrize("index, pair", [(0, True), (1, False)])
def test_an_element_out_of_a_tuple_depends_on_that_element_only(index, pair):
    """HLO text: the second LU takes element `index` of a barrier over (p1, first LU's
    result). Element 0 is p1, which needs nothing: a pair although an HLO path runs
    through the tuple; element 1 is the first LU's result: ordered, no pair."""
    found = runtime.concurrent_lapack_calls(HLO_TUPLE.replace("INDEX", str(index)))
    assert [(a.name, b.name) for a, b in found] == ([("lu.1", "lu.2")] if pair else [])


def test_a_loop_with_a_batched_call_beside_another_is_a_pair():
    a, x = mats(200)

    def f(a, b, x):
        def body(i, y):
            return jnp.linalg.solve(a, y) * 0.5
        return jax.lax.fori_loop(0, 3, body, x), jnp.linalg.eigvalsh(b + jnp.swapaxes(b, 1, 2))

    pairs = runtime.concurrent_lapack_calls(compiled(f, a, a + 1, x))
    assert [tuple(sorted(p)) for p in pair_names(pairs)] == [("dgetrf", "dsyevd")]


def test_the_lowered_text_is_refused():
    a, x = mats(4)
    with pytest.raises(ValueError, match="HloModule"):
        runtime.concurrent_lapack_calls(jax.jit(jnp.linalg.solve).lower(a, x))


def certificate_program(drive, observer, **kw):
    """The compiled program of `slowly_varying_certificate` (its `_certificate`)."""
    seen = {}
    original = _lyapunov._certificate

    def spy(*args):
        seen["args"] = args
        return original(*args)

    _lyapunov._certificate = spy
    try:
        analysis.slowly_varying_certificate(drive, observer, (0.1, 1.0), **kw)
    finally:
        _lyapunov._certificate = original
    return original.lower(*seen["args"]).compile()


def test_the_certificate_runs_its_batched_lapack_calls_one_after_the_other():
    """At notebook 03's resolution; with `min_work=1` every batched call counts, so no
    finer grid (more speeds, times or alphas) can form a pair either."""
    drive = pj.preset("zhang750")
    prog = certificate_program(drive, make_observer("leso", drive, w2=2 * math.pi * 50.0))
    assert runtime.concurrent_lapack_calls(prog, min_work=1) == []
