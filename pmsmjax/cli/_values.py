"""The values of the command line's options: the argument types (finite and positive
numbers, integers, `NAME=VALUE`, the `LO:HI:N` grids, the `LO:HI` speed range), the list
option (`--speeds 0.2 0.6`), and `CLIError`, the user error.

A bad value raises `argparse.ArgumentTypeError` while parsing, or `CLIError` after it;
`pmsmjax.cli.main` prints either as one line and exits with status 2.
"""

from __future__ import annotations

import argparse
import math
import re

import numpy as np


class CLIError(Exception):
    """A user error: printed as one line, exit status 2."""


def _number(text: str, what: str = "value") -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what} {text.strip()!r} is not a number") from None
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"{what} {text.strip()!r} must be finite")
    return x


def finite_float(text: str) -> float:
    return _number(text)


def positive_float(text: str) -> float:
    x = _number(text)
    if not x > 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number > 0")
    return x


def nonneg_float(text: str) -> float:
    x = _number(text)
    if not x >= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number >= 0")
    return x


def _int_at_least(text: str, lo: int) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if n < lo:
        raise argparse.ArgumentTypeError(f"{text!r} must be an integer >= {lo}")
    return n


def positive_int(text: str) -> int:
    return _int_at_least(text, 1)


def nonneg_int(text: str) -> int:
    return _int_at_least(text, 0)


def name_value(text: str) -> tuple[str, float]:
    """`NAME=VALUE` with a finite number VALUE."""
    name, sep, value = text.partition("=")
    name = name.strip()
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"{text!r} is not of the form NAME=VALUE")
    try:
        x = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"the value in {text!r} is not a number (SI units, e.g. L_q=2.7e-3)") from None
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"the value in {text!r} must be finite")
    return name, x


def grid(*, nonneg: bool):
    """Type of a `LO:HI:N` grid option (N points from LO to HI inclusive); a single
    number X is X:X:1. Returns `(lo, hi, n)`."""

    def parse(text: str):
        parts = text.split(":")
        if len(parts) == 1:
            parts = [parts[0], parts[0], "1"]
        if len(parts) != 3:
            raise argparse.ArgumentTypeError(
                f"{text!r} is not LO:HI:N (N points from LO to HI inclusive, e.g. 0:5:101) "
                f"or a single number")
        lo, hi = _number(parts[0], "LO"), _number(parts[1], "HI")
        try:
            n = int(parts[2])
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"N in {text!r} must be an integer >= 1; got {parts[2].strip()!r}") from None
        if n < 1:
            raise argparse.ArgumentTypeError(f"N in {text!r} must be an integer >= 1")
        if nonneg and lo < 0:
            raise argparse.ArgumentTypeError(f"LO in {text!r} must be >= 0 (allowed: "
                                             f"0 <= LO <= HI)")
        if lo > hi:
            raise argparse.ArgumentTypeError(f"LO > HI in {text!r} (allowed: LO <= HI)")
        if n == 1 and lo != hi:
            raise argparse.ArgumentTypeError(f"N = 1 in {text!r} needs LO = HI (or give a "
                                             f"single number)")
        if n > 1 and lo == hi:
            raise argparse.ArgumentTypeError(f"LO = HI in {text!r} needs N = 1")
        return lo, hi, n

    return parse


def named_grid(text: str) -> tuple[str, tuple[float, float, int]]:
    """`NAME=LO:HI:N` (a design parameter and its grid); returns `(name, (lo, hi, n))`."""
    name, sep, spec = text.partition("=")
    name = name.strip()
    if not sep or not name or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not NAME=LO:HI:N (a design parameter and N points from LO to HI "
            f"inclusive, e.g. zeta1=0:5:101)")
    try:
        return name, grid(nonneg=False)(spec)
    except argparse.ArgumentTypeError as e:
        raise argparse.ArgumentTypeError(f"{text!r}: {e}") from None


def grid_values(spec) -> np.ndarray:
    """The points of a parsed `LO:HI:N` grid (float64, N of them)."""
    lo, hi, n = spec
    return np.linspace(lo, hi, n)


def speed_range(text: str) -> tuple[float, float]:
    parts = text.split(":")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"{text!r} is not LO:HI (p.u., 0 < LO < HI, e.g. "
                                         f"0.1:1)")
    lo, hi = _number(parts[0], "LO"), _number(parts[1], "HI")
    if not lo > 0:
        raise argparse.ArgumentTypeError(
            f"LO in {text!r} must be > 0 (allowed: 0 < LO < HI, p.u.): the flux gains of "
            f"the zhang2022 designs vanish at w0 = 0 (w1 is proportional to |w0| in the "
            f"ratio and zhang2022 (38) designs), so A is not Hurwitz there and no "
            f"certificate covers standstill")
    if not lo < hi:
        raise argparse.ArgumentTypeError(f"{text!r} needs LO < HI (allowed: 0 < LO < HI, "
                                         f"p.u.)")
    return lo, hi


class ListOption(argparse.Action):
    """A list option: space-separated values (`nargs="+"`), each converted by `item`;
    repeating the option adds to the list (with `groups=True` each occurrence is one
    group, a list of lists). A value with a comma is refused with the spaced form of this
    option (or of `plural`, for a one-value option, `nargs=None`) in the message."""

    def __init__(self, option_strings, dest, *, item=str, groups: bool = False,
                 plural: str | None = None, **kw):
        self.item = item
        self.groups = groups
        self.plural = plural  # the list option to suggest (for a one-value option)
        kw.setdefault("nargs", "+")
        super().__init__(option_strings, dest, **kw)

    def __call__(self, parser, namespace, values, option_string=None):
        items = []
        for v in [values] if isinstance(values, str) else values:
            if "," in v:
                spaced = " ".join(x.strip() for x in v.split(","))
                raise argparse.ArgumentError(
                    self, f"{v!r}: give the values separated by spaces, e.g. "
                          f"{self.plural or option_string} {spaced}")
            try:
                items.append(self.item(v.strip()))
            except argparse.ArgumentTypeError as e:
                raise argparse.ArgumentError(self, str(e)) from None
            except ValueError:
                raise argparse.ArgumentError(self, f"invalid value {v.strip()!r}") from None
        cur = getattr(namespace, self.dest, None)
        cur = list(cur) if cur is not None and cur is not self.default else []
        setattr(namespace, self.dest, cur + ([items] if self.groups else items))


# Values that start with a minus sign but are not plain numbers (-1:1, -1e-3); argparse's
# own pattern only accepts -12 and -1.5. (`--speed=-1e-3` works either way.)
_NEGATIVE_VALUE = re.compile(r"^-\.?[0-9][0-9.eE+\-:]*$")


def allow_negative_values(parser: argparse.ArgumentParser) -> None:
    """Let `parser` read `-1:1` and `-1e-3` as values, not as unknown options."""
    if hasattr(parser, "_negative_number_matcher"):
        parser._negative_number_matcher = _NEGATIVE_VALUE
