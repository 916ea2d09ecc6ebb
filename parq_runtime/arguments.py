"""Command-line parsing shared by every parq-* command: bad arguments give one line.

argparse prints its usage block before the error; the package's rule is one line saying what
is wrong, exit code 2, as for every other error (ParqError at the CLI edge).  The converters
below say what was expected in that line.
"""
from __future__ import annotations

import argparse
import math


class OneLineParser(argparse.ArgumentParser):
    """ArgumentParser whose errors are ``PROG: error: MESSAGE (see PROG --help)``, exit 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def integer(text: str) -> int:
    try:
        return int(text, 10)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None


def at_least(convert, limit):
    """``convert`` (an argument type) with a lower bound."""
    def checked(text: str):
        value = convert(text)
        if value < limit:
            raise argparse.ArgumentTypeError(f"{value} must be at least {limit}")
        return value
    checked.__name__ = convert.__name__
    return checked


positive_int = at_least(integer, 1)


def non_negative_int(text: str) -> int:
    value = integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value} must not be negative")
    return value


def number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None


def non_negative_float(text: str) -> float:
    value = number(text)
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"{value} must not be negative")
    return value


def positive_float(text: str) -> float:
    value = number(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{value} must be above 0")
    return value


def at_most(convert, limit):
    """``convert`` (an argument type) with an upper bound: a larger value is a mistyped one."""
    def checked(text: str):
        value = convert(text)
        if value > limit:
            raise argparse.ArgumentTypeError(f"{value} must be at most {limit}")
        return value
    checked.__name__ = convert.__name__
    return checked


def finite(convert):
    """``convert`` (a float argument type) refusing inf and nan first."""
    def checked(text: str) -> float:
        value = number(text)
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{value} is not a finite number")
        return convert(text)
    checked.__name__ = convert.__name__
    return checked


def fraction(text: str) -> float:
    value = number(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"{value} must be between 0 and 1")
    return value


def score(text: str) -> float:
    value = number(text)
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"{value} must be at least 0 and below 1")
    return value


def scene_nms(text: str):
    """An IoU in [0, 1) (as :func:`score`), or SCENE_NMS_OFF."""
    from .fusion import SCENE_NMS_OFF

    if text.strip().lower() == SCENE_NMS_OFF:
        return SCENE_NMS_OFF
    try:
        return score(text)
    except argparse.ArgumentTypeError as e:
        raise argparse.ArgumentTypeError(f"{e}, or {SCENE_NMS_OFF!r}") from None


def floor_height(text: str):
    """A height in metres along the world's up axis, or FLOOR_OFF."""
    from .fusion import FLOOR_OFF

    if text.strip().lower() == FLOOR_OFF:
        return FLOOR_OFF
    try:
        value = number(text)
    except argparse.ArgumentTypeError as e:
        raise argparse.ArgumentTypeError(f"{e}, or {FLOOR_OFF!r}") from None
    if not math.isfinite(value) or abs(value) > 1e5:
        raise argparse.ArgumentTypeError(f"{value} is not a height in metres (within 100 km "
                                         f"of the origin), or {FLOOR_OFF!r}")
    return value


def match_iou(text: str) -> float:
    """An IoU in (0, 1]: the fusion's matching floor (parq_runtime.fusion)."""
    value = number(text)
    if not 0.0 < value <= 1.0:
        raise argparse.ArgumentTypeError(f"{value} must be above 0 and at most 1")
    return value


def ray_ratio(text: str) -> float:
    value = number(text)
    if not 1.0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"{value} must be at least 1 (1 is the mean fusion)")
    return value
