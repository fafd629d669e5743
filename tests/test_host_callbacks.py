"""Where the library's programs call back into Python (host callbacks).

Public reports of CPU programs that hang under asynchronous dispatch need a host callback
(`jax.debug.callback`, `jax.pure_callback`; `equinox.error_if` lowers to one inside a
`lax.cond`) inside a `while` loop, run many times. These tests pin down that the analyses
that hung (the Lyapunov certificate, the generic equilibria) contain no host callback at
all, and that the closed loop calls the host only outside its time loop, and only when
asked to raise (`throw=True`). The check walks the jaxpr, so it covers the jitted and the
eager (un-jitted `vmap`) call alike; benchmarks/reproducers/stress_hang.py measures the hangs.
"""

import jax
import jax.numpy as jnp
import pytest

import pmsmjax as pj
from pmsmjax import analysis


CALLBACKS = frozenset({"pure_callback", "io_callback", "debug_callback"})
LOOPS = frozenset({"while", "scan"})


def _subjaxprs(value):
    if hasattr(value, "eqns"):  # a Jaxpr
        yield value
    elif hasattr(value, "jaxpr") and hasattr(value.jaxpr, "eqns"):  # a ClosedJaxpr
        yield value.jaxpr
    elif isinstance(value, (tuple, list)):
        for v in value:
            yield from _subjaxprs(v)


def host_callbacks(closed_jaxpr) -> list[tuple[str, bool]]:
    """Every host callback of a program: `(primitive, inside a while/scan loop)`."""
    found = []

    def walk(jaxpr, in_loop):
        for eqn in jaxpr.eqns:
            name = eqn.primitive.name
            if name in CALLBACKS:
                found.append((name, in_loop))
            for v in eqn.params.values():
                for sub in _subjaxprs(v):
                    walk(sub, in_loop or name in LOOPS)

    walk(closed_jaxpr.jaxpr, False)
    return found


@pytest.fixture(scope="module")
def drive():
    return pj.preset("zhang750")


def test_the_walker_finds_a_callback_in_a_loop_and_one_after_it():
    def f(x):
        def body(c):
            jax.debug.callback(lambda v: None, c[1])
            return c[0] + 1, 0.5 * c[1]
        y = jax.lax.while_loop(lambda c: c[0] < 3, body, (0, x))[1]
        return jax.pure_callback(lambda v: v, jax.ShapeDtypeStruct((), y.dtype), y)

    assert sorted(host_callbacks(jax.make_jaxpr(f)(1.0))) == [
        ("debug_callback", True), ("pure_callback", False)]


def test_the_certificate_and_the_generic_equilibria_have_no_host_callback(drive):
    obs = pj.observers.make_observer("leso", drive)

    def cert(zeta1):
        return analysis.slowly_varying_certificate(
            drive, obs.with_design(zeta1=zeta1, ratio=0.5), (0.2, 1.0), n_speed=3,
            n_time=4, n_dirs=4, n_refine=2, n_k1_speeds=2).eps

    # vmapped and not jitted, as the notebook that hung called it
    assert host_callbacks(jax.make_jaxpr(jax.vmap(cert))(jnp.array([0.8, 1.0]))) == []
    eq = jax.make_jaxpr(lambda w: analysis.equilibria(
        obs, drive.motor, w, jnp.array([0.0, 0.5]), method="generic").status)
    assert host_callbacks(eq(0.5 * float(drive.w_rated))) == []


def test_the_closed_loop_calls_the_host_only_after_its_time_loop(drive):
    foc, obs = pj.FOC.from_drive(drive), pj.ESOObserver.from_drive(drive)

    def run(w, throw):
        sc = pj.Scenario(t_end=8 * 125e-6, w_m_ref=pj.Profile.ramp(0.0, 0.1, 0.0, w))
        return pj.simulate(drive, foc, obs, sc, T_s=125e-6, throw=throw).ise_theta

    w = 0.3 * float(drive.w_rated)
    raising = host_callbacks(jax.make_jaxpr(lambda w: run(w, True))(w))
    assert raising and all(not in_loop for _, in_loop in raising)
    assert host_callbacks(jax.make_jaxpr(lambda w: run(w, False))(w)) == []


def test_no_registered_observer_calls_the_host_inside_the_time_loop(drive):
    """Every observer's `step` runs inside `simulate`'s time loop: none may call the host
    there (an `eqx.error_if` in a `step` would put a host callback in the loop)."""
    from pmsmjax.observers import make_observer, observer_names

    foc = pj.FOC.from_drive(drive)
    in_loop = {}
    for name in observer_names():
        obs = make_observer(name, drive)

        def run(w, obs=obs):
            sc = pj.Scenario(t_end=4 * 125e-6, w_m_ref=pj.Profile.ramp(0.0, 0.1, 0.0, w))
            return pj.simulate(drive, foc, obs, sc, T_s=125e-6, throw=True).ise_theta
        jaxpr = jax.make_jaxpr(run)(0.3 * float(drive.w_rated))
        in_loop[name] = [p for p, inside in host_callbacks(jaxpr) if inside]
    assert len(in_loop) >= 3 and not any(in_loop.values()), in_loop
