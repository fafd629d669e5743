"""Stored programs: a traced program kept with `jax.export` (StableHLO), so that a repeated
command skips Python's tracing and lowering as well as XLA's compile (`stored_call`; the
package docstring says when they are on)."""

from __future__ import annotations

from pathlib import Path

import jax

from .._files import atomic_write


#: Sub-directory of `cache_dir()` with the stored (exported) programs.
STORED_SUBDIR = "exported"
_STORE_DIR: Path | None = None  # set by `configure` when the cache is on
_SOURCE_HASH: str | None = None


class _Unkeyable(Exception):
    """A static value whose identity cannot be written down stably (a lambda, a closure,
    an object whose repr is its address): such a call is not stored."""


def stored_programs_dir() -> Path | None:
    """Where `stored_call` keeps its programs (`cache_dir()/exported`), or None when
    `configure` did not turn the compilation cache on in this process."""
    return _STORE_DIR


def set_stored_programs_dir(d: Path | None) -> None:
    """Keep the stored programs in `d` from now on; None turns them off (`configure`)."""
    global _STORE_DIR
    _STORE_DIR = d


def _can_serialize() -> bool:
    """`jax.export`'s serialisation needs the `flatbuffers` package (a dependency of
    pmsmjax); without it nothing is stored and every call traces as before."""
    import importlib.util

    return importlib.util.find_spec("flatbuffers") is not None


def _source_hash() -> str:
    """SHA-256 of every Python source file of the pmsmjax package (paths and contents):
    any change of the code invalidates every stored program."""
    global _SOURCE_HASH
    if _SOURCE_HASH is None:
        import hashlib

        root = Path(__file__).resolve().parents[1]  # pmsmjax/ (this is runtime/_stored.py)
        h = hashlib.sha256()
        for p in sorted(root.rglob("*.py")):
            h.update(str(p.relative_to(root)).encode())
            h.update(b"\0")
            h.update(p.read_bytes())
            h.update(b"\0")
        _SOURCE_HASH = h.hexdigest()
    return _SOURCE_HASH


def _describe(x, depth: int = 0):
    """A stable, hashable description of `x` for the key of a stored program: arrays by
    shape, dtype and weak type (their values are the program's inputs), every other value
    (the static part, baked into the program) by type and value; dataclasses (equinox
    modules) field by field with their class's module and name. Raises `_Unkeyable` for
    anything else (lambdas, closures, objects without a stable repr)."""
    import dataclasses
    import enum
    import types

    import numpy as np

    if depth > 64:
        raise _Unkeyable("nested too deeply")
    if isinstance(x, jax.Array | np.ndarray | np.generic):
        return ("array", tuple(x.shape), str(x.dtype), bool(getattr(x, "weak_type", False)))
    if x is None or isinstance(x, bool | int | float | complex | str | bytes):
        return (type(x).__name__, repr(x))
    if isinstance(x, enum.Enum):
        return ("enum", type(x).__module__, type(x).__qualname__, x.name)
    if isinstance(x, tuple | list):
        return (type(x).__name__, tuple(_describe(v, depth + 1) for v in x))
    if isinstance(x, dict):
        return ("dict", tuple(sorted((repr(k), _describe(v, depth + 1))
                                     for k, v in x.items())))
    if isinstance(x, types.FunctionType):
        if x.__closure__ or "<" in x.__qualname__:
            raise _Unkeyable(f"function {x.__qualname__}")
        return ("function", x.__module__, x.__qualname__)
    if isinstance(x, types.MethodType):
        return ("method", _describe(x.__self__, depth + 1), x.__func__.__qualname__)
    if isinstance(x, type):
        return ("type", x.__module__, x.__qualname__)
    if dataclasses.is_dataclass(x):
        cls = type(x)
        return ("dataclass", cls.__module__, cls.__qualname__,
                tuple((f.name, _describe(getattr(x, f.name, None), depth + 1))
                      for f in dataclasses.fields(x)))
    raise _Unkeyable(f"value of type {type(x).__qualname__}")


def _program_key(tag: str, fn, args) -> str | None:
    import hashlib

    import jaxlib

    from .. import __version__

    try:
        desc = (tag, _describe(fn), _describe(args))
    except _Unkeyable:
        return None
    parts = (repr(desc), __version__, _source_hash(), jax.__version__, jaxlib.__version__,
             repr(jax.config.jax_enable_x64), jax.default_backend())
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


_LOADED: dict = {}  # key -> the jitted call of a program read in this process


def _call_exported(key: str, blob: bytes | None, leaves, out_type):
    call = _LOADED.get(key)
    if call is None:
        exp = jax.export.deserialize(bytearray(blob))
        if [(tuple(a.shape), a.dtype) for a in exp.in_avals] != [(tuple(v.shape), v.dtype)
                                                                 for v in leaves]:
            raise ValueError("stored program: its inputs differ from the call's")
        call = jax.jit(exp.call)
    # every input committed to the default device: a call with the outputs of an earlier
    # one (committed) then has the same signature as one with fresh arrays, and reuses
    # its compiled program instead of reading another from the cache
    out = call(*jax.device_put(leaves, jax.devices()[0]))
    _LOADED[key] = call
    import dataclasses

    names = [f.name for f in dataclasses.fields(out_type)]
    if len(out) != len(names):
        raise ValueError("stored program: its outputs differ from the result type's")
    return out_type(**dict(zip(names, out)))


def stored_call(tag: str, fn, args: tuple, out_type):
    """`fn(*args)` through a stored program, or None (the caller then runs `fn` its own
    way): None when `configure` did not turn the cache on, when a static value in `args`
    has no stable description, or when exporting fails.

    `fn` must be a pure function, traceable by JAX, whose result is an instance of the
    dataclass `out_type` (an equinox module) with array fields; the array leaves of `args`
    are its inputs and every other leaf is static (as `equinox.filter_jit` treats them).
    The program is stored (`jax.export`, StableHLO) under a key made of `tag`, `fn`, the
    static leaves and the shapes and dtypes of the array leaves, the pmsmjax version and a
    hash of its source, the jax/jaxlib versions, `jax_enable_x64` and the backend; a
    stored program that cannot be read, does not match or fails is deleted and made
    again from a fresh trace. XLA's compile of the stored program then hits the persistent
    compilation cache like any other program.
    """
    d = _STORE_DIR
    if d is None or not _can_serialize():
        return None
    import equinox as eqx

    dyn, static = eqx.partition(args, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dyn)
    if any(isinstance(v, jax.core.Tracer) for v in leaves):
        return None  # called inside a transformation: trace as usual
    key = _program_key(tag, fn, args)
    if key is None:
        return None
    # the source hash in the name: programs of an older pmsmjax are removed (below)
    stem = f"{tag}-{_source_hash()[:12]}-"
    path = d / f"{stem}{key}.jaxexport"
    if key in _LOADED:
        return _call_exported(key, None, leaves, out_type)
    if path.is_file():
        try:
            return _call_exported(key, path.read_bytes(), leaves, out_type)
        except Exception:  # noqa: BLE001 - corrupt or stale: make it again
            try:
                path.unlink()
            except OSError:
                pass
    import dataclasses

    names = [f.name for f in dataclasses.fields(out_type)]

    def flat(*xs):
        out = fn(*eqx.combine(jax.tree_util.tree_unflatten(treedef, list(xs)), static))
        if not isinstance(out, out_type):
            raise TypeError(f"stored_call: {tag} returned {type(out).__name__}, not "
                            f"{out_type.__name__}")
        return tuple(getattr(out, n) for n in names)

    try:
        # every custom call allowed (LAPACK's QR and eigensolvers have no compatibility
        # guarantee across jaxlib versions): the key pins jax, jaxlib and the backend, so
        # a stored program only ever runs on the jaxlib that wrote it
        blob = bytes(jax.export.export(jax.jit(flat), disabled_checks=[
            jax.export.DisabledSafetyCheck.custom_call("ALL")])(
            *leaves).serialize())
    except Exception:  # noqa: BLE001 - not exportable: the caller traces as usual
        return None
    try:
        d.mkdir(parents=True, exist_ok=True)
        atomic_write(path, blob)
        for old in d.glob(f"{tag}-*.jaxexport"):  # stored by another version of the code
            if not old.name.startswith(stem):
                old.unlink(missing_ok=True)
    except OSError:
        pass  # read-only or full: still run the program just made
    # the same route as a later process (deserialise, call): same compiled program
    try:
        return _call_exported(key, blob, leaves, out_type)
    except Exception:  # noqa: BLE001
        return None
