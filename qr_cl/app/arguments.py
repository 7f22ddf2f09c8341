"""Command-line checks shared by every ``qr-cl`` command and the bench scripts, defined once.

Sizes, counts and steps are checked where a command parses them: argparse ``type=`` functions
that raise :class:`argparse.ArgumentTypeError` with what was expected, and a parser whose
errors are one line (``qr-cl render: error: argument --width: expected a positive integer, got
-5``) with exit status 2, no usage block and no traceback.
"""
from __future__ import annotations

import argparse
from typing import NoReturn


class OneLineParser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose errors are one line on stderr (exit status 2);
    the sub-parsers it makes are of this class too."""

    def error(self, message: str) -> NoReturn:
        """Print ``<prog>: error: <message> (<prog> --help)`` and exit with status 2."""
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _integer(text: str, what: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None


def _number(text: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1 (a size in px, a count, a number of steps)."""
    value = _integer(text, "a positive integer")
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return value


def nonnegative_int(text: str) -> int:
    """An integer >= 0 (an index, a seed, a level, a count where 0 means none)."""
    value = _integer(text, "an integer >= 0")
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0 (a length, a rate, a time)."""
    value = _number(text, "a positive number")
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return value


def port_number(text: str) -> int:
    """A TCP port, 0 to 65535 (0: any free one)."""
    value = _integer(text, "a port number (0 to 65535)")
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"expected a port number (0 to 65535), got {text}")
    return value


#: ``choices`` of an up-axis option: the world axis that points up (0 = x, 1 = y, 2 = z).
AXES = (0, 1, 2)

