"""Which batched LAPACK calls of a compiled CPU program can deadlock XLA's thread pool.

jaxlib runs LAPACK (`jnp.linalg.solve`, `eigvals`, `eigvalsh`, `jax.scipy.linalg.expm`,
...) on the CPU as custom calls. A call on a batch of matrices whose estimated work
(batch x FLOP per matrix) reaches `LAPACK_MIN_WORK` splits the batch into chunks,
schedules them on XLA's intra-op thread pool and *blocks its own pool thread* until they
are done. XLA also runs independent parts of one program at the same time on that pool.
When every pool thread is blocked in such a call, the chunks they wait for can never run:
the program deadlocks (all threads asleep, the caller waiting for its result). The pool
has one thread per core, so on a 2-core machine two such calls that run at the same time
are enough. (jaxlib 0.10.2, `jaxlib/cpu/lapack_kernels.cc`: `GetLapackBatchChunkSize`,
`ParallelBatchMap`; reproduced with `slowly_varying_certificate` and native stacks,
BENCHMARKS.md.)

`concurrent_lapack_calls` reads the optimised HLO of a compiled program and returns the
pairs of chunked LAPACK calls (or loops and calls that contain one) with no data or
control dependency between them: the pairs XLA may run at the same time. A program
without such a pair cannot deadlock this way, whatever the pool size.
"""

from __future__ import annotations

import re
from dataclasses import dataclass


#: jaxlib's `kMinWorkPerTask` (FLOP): a batched LAPACK call with less estimated work runs
#: inline on its own thread and cannot block.
LAPACK_MIN_WORK = 200_000

_HEADER = re.compile(r"^(?:ENTRY )?%?([\w.\-]+) \(.*\) -> .*\{$")
_INSTR = re.compile(r"^\s+(?:ROOT )?%([\w.\-]+) = (.*)$")
_REF = re.compile(r"%([\w.\-]+)")
_TARGET = re.compile(r'custom_call_target="lapack_([sdcz])(\w+?)_ffi"')
_SHAPE = re.compile(r"\b(f32|f64|c64|c128)\[([\d,]*)\]")


def _flop(routine: str, m: int, n: int, y: tuple[int, ...] | None) -> int:
    """jaxlib 0.10.2's estimate of the FLOP per matrix (before the complex factor 3);
    an unknown routine gets the largest of them (10 m n k), which errs on the safe side."""
    k = min(m, n)
    if routine == "trsm" and y is not None and len(y) >= 2:
        r, c = y[-2], y[-1]
        return r * c * max(r, c)
    table = {
        "getrf": m * n * k,
        "geqrf": 2 * m * n * k - 2 * k ** 3 // 3,
        "geqp3": 2 * m * n * k - 2 * k ** 3 // 3,
        "orgqr": 4 * m * n * k - 2 * k * k * (m + n) + 4 * k ** 3 // 3,
        "potrf": n ** 3 // 3,
        "syevd": 5 * n ** 3,
        "heevd": 4 * n ** 3,
        "geev": 10 * n ** 3,
        "gees": 5 * n ** 3,
        "gehrd": 2 * n ** 3,
        "sytrd": 4 * n ** 3 // 3,
        "hetrd": 4 * n ** 3 // 3,
    }
    return table.get(routine, 10 * m * n * k)


@dataclass(frozen=True)
class LapackCall:
    """One batched LAPACK custom call: `name` (HLO instruction), `routine` (e.g.
    `"dgetrf"`), `batch` (matrices), `shape` (one matrix), `work` (estimated FLOP)."""

    name: str
    routine: str
    batch: int
    shape: tuple[int, int]
    work: int


def _lapack_call(name: str, rhs: str) -> LapackCall | None:
    t = _TARGET.search(rhs)
    if t is None:
        return None
    # operand shapes: printed with the operands, or (compiled HLO) in the layout
    # constraints; else the result's
    head, _, tail = rhs.partition("custom-call(")
    ops = tail.split("custom_call_target")[0]
    if "operand_layout_constraints={" in tail:
        ops = tail.split("operand_layout_constraints={", 1)[1].split("}}", 1)[0]
    shapes = [(dt, tuple(int(d) for d in dims.split(",") if d))
              for dt, dims in (_SHAPE.findall(ops) or _SHAPE.findall(head))]
    if not shapes or len(shapes[0][1]) < 2:
        return None
    dt, x = shapes[0]
    y = shapes[1][1] if len(shapes) > 1 else None
    batch = 1
    for d in x[:-2]:
        batch *= d
    m, n = x[-2], x[-1]
    work = batch * _flop(t.group(2), m, n, y) * (3 if dt.startswith("c") else 1)
    return LapackCall(name, t.group(1) + t.group(2), batch, (m, n), work)


def _parse(hlo: str):
    comps: dict[str, list[tuple[str, str]]] = {}
    cur = None
    for line in hlo.splitlines():
        h = _HEADER.match(line)
        if h:
            cur = comps.setdefault(h.group(1), [])
            continue
        if line.startswith("}"):
            cur = None
            continue
        i = _INSTR.match(line) if cur is not None else None
        if i:
            cur.append((i.group(1), i.group(2)))
    return comps


_GTE = re.compile(r"get-tuple-element\(%([\w.\-]+)\), index=(\d+)")


def _through_tuples(ref: str, rhs_of: dict) -> str:
    """The instruction whose buffer an element taken out of a tuple really is.

    A `tuple` and an `opt-barrier` make no work of their own at run time: an element taken
    out of them (`get-tuple-element`) is the buffer of the tuple's operand, so the user
    depends on that operand only, not on the tuple's other elements. (An
    `optimization_barrier` thus orders nothing at run time.)"""
    while True:
        m = _GTE.search(rhs_of.get(ref, ""))
        if m is None:
            return ref
        src, idx = m.group(1), int(m.group(2))
        src_rhs = rhs_of.get(src, "")
        while " opt-barrier(" in src_rhs:  # the barrier's operand is a tuple
            src = _REF.findall(src_rhs)[0]
            src_rhs = rhs_of.get(src, "")
        if " tuple(" not in src_rhs:
            return ref
        ops = _REF.findall(src_rhs.split(" tuple(", 1)[1])
        if idx >= len(ops):
            return ref
        ref = ops[idx]


def concurrent_lapack_calls(compiled, min_work: int = LAPACK_MIN_WORK
                            ) -> list[tuple[LapackCall, LapackCall]]:
    """The pairs of chunked LAPACK calls that XLA may run at the same time (see the module
    docstring); empty when the program cannot deadlock XLA's pool this way.

    - `compiled`: the optimised HLO text, or an object with `as_text()` (a
      `jax.stages.Compiled`, i.e. `jax.jit(f).lower(*args).compile()`), or with a
      `.compiled` attribute that has it (`equinox.filter_jit(f).lower(*args).compile()`).
    - `min_work`: estimated FLOP from which a call is chunked (jaxlib's threshold).

    Each pair names the two calls themselves, also when one sits inside a loop or a
    called computation that runs beside the other. Dependencies are the operands of XLA's
    graph, except that an element taken out of a tuple (or of an `optimization_barrier`)
    depends on that element only: neither does any work at run time, so neither orders
    anything (XLA also drops a barrier that has nothing to keep apart).
    """
    if not isinstance(compiled, str):
        inner = getattr(compiled, "compiled", compiled)
        if not hasattr(inner, "as_text"):
            raise ValueError("`concurrent_lapack_calls(compiled)` needs HLO text or a "
                             f"compiled program with `as_text()`; got {type(compiled)}.")
        compiled = inner.as_text()
    if not compiled.lstrip().startswith("HloModule"):
        raise ValueError("`concurrent_lapack_calls(compiled)` reads XLA's HLO text (it starts "
                         "with 'HloModule'), as a compiled program's `as_text()` gives it; "
                         "a lowered program's text (StableHLO) is not it: compile it first.")
    comps = _parse(compiled)
    memo: dict[str, list[LapackCall]] = {}

    def calls_in(comp: str) -> list[LapackCall]:  # a computation's, nested ones included
        if comp not in memo:
            memo[comp] = [c for name, rhs in comps[comp] for c in own(name, rhs)]
        return memo[comp]

    def own(name: str, rhs: str) -> list[LapackCall]:  # an instruction's: itself or callees
        call = _lapack_call(name, rhs)
        if call is not None:
            return [call] if call.work >= min_work and call.batch > 1 else []
        return [c for ref in _REF.findall(rhs) if ref in comps for c in calls_in(ref)]

    pairs = []
    for comp, instrs in comps.items():
        local = {name for name, _ in instrs}
        rhs_of = dict(instrs)
        deps = {name: [_through_tuples(r, rhs_of) for r in _REF.findall(rhs)
                       if r in local and r != name]
                for name, rhs in instrs}
        heavy = [(name, own(name, rhs)) for name, rhs in instrs]
        heavy = [(name, calls) for name, calls in heavy if calls]
        if len(heavy) < 2:
            continue
        anc: dict[str, set[str]] = {}

        def ancestors(x):
            if x not in anc:
                seen, stack = set(), list(deps[x])
                while stack:
                    y = stack.pop()
                    if y not in seen:
                        seen.add(y)
                        stack.extend(deps.get(y, ()))
                anc[x] = seen
            return anc[x]

        for i, (a, ca) in enumerate(heavy):
            for b, cb in heavy[i + 1:]:
                if a not in ancestors(b) and b not in ancestors(a):
                    pairs.append((ca[0], cb[0]))
    return pairs
