"""Numeric command-line options checked when they are parsed, the range in the message.

A number that parses is not yet one a command can use: `--epochs 0` would do nothing and exit 0,
`--batch -1` would process no image, `--time inf` would overflow after an hour of training and
`--seed 10**24` would fail after writing the first frame's files. Every numeric option of every
command is therefore given one of these types, so argparse refuses it before anything runs:

    omnigen train: error: argument --batch: 0 is outside [1, 4096]

NaN is refused by every float type; infinity unless the range itself is unbounded on that side
and `allow_inf` asks for it.
"""

from __future__ import annotations

import argparse
import math
from typing import Callable

SEED_MAX = 2**63 - 1  # numpy's SeedSequence takes any non-negative int; the records store it as int64


def _range_text(lo: float | None, hi: float | None, lo_open: bool = False, hi_open: bool = False) -> str:
    left = "(" if lo_open or lo is None else "["
    right = ")" if hi_open or hi is None else "]"
    return f"{left}{'-inf' if lo is None else _num(lo)}, {'inf' if hi is None else _num(hi)}{right}"


def _num(x: float) -> str:
    """A bound as the user would type it: ints whole (2**63 - 1 to the last digit), floats short."""
    if isinstance(x, int):
        return str(x)
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


def integer(lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """An int in [lo, hi] (either bound may be None)."""
    def parse(text: str) -> int:
        try:
            value = int(text, 10)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(f"{text} is outside {_range_text(lo, hi)}")
        return value

    parse.__name__ = "integer"  # argparse names the type in its own messages
    return parse


def number(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
           hi_open: bool = False, allow_inf: bool = False) -> Callable[[str], float]:
    """A finite float in the range (bounds closed unless `lo_open` / `hi_open`)."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if math.isnan(value) or (math.isinf(value) and not allow_inf):
            raise argparse.ArgumentTypeError(f"{text} is not a finite number; expected one in "
                                             f"{_range_text(lo, hi, lo_open, hi_open)}")
        bad = ((lo is not None and (value < lo or (lo_open and value == lo)))
               or (hi is not None and (value > hi or (hi_open and value == hi))))
        if bad:
            raise argparse.ArgumentTypeError(f"{text} is outside {_range_text(lo, hi, lo_open, hi_open)}")
        return value

    parse.__name__ = "number"
    return parse


def seed() -> Callable[[str], int]:
    """A random seed: a whole number in [0, 2**63 - 1], what the records and numpy both hold."""
    return integer(0, SEED_MAX)


def fraction(lo_open: bool = False, hi_open: bool = False) -> Callable[[str], float]:
    """A float in [0, 1]."""
    return number(0.0, 1.0, lo_open=lo_open, hi_open=hi_open)
