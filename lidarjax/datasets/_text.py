"""Strict tokens and numbers for the text readers.

Python's ``float()`` and ``int()`` are lenient in ways a data file must not be: ``"1_5"`` is
15, and (on ``str``) NBSP, NEL and the ASCII file/group/record/unit separators count as
whitespace. The text readers therefore work on ``bytes`` (``bytes.split()`` separates at ASCII
whitespace only: space, ``\\t``, ``\\n``, ``\\r``, ``\\v``, ``\\f``) and accept exactly these
numbers:

- decimal: ``[+-]? (digits [. digits?] | . digits) ([eE] [+-]? digits)?``
- non-finite (only where the caller allows them): ``[+-]? (nan | inf | infinity)``, any case
- integer: ``[+-]? digits`` (``digits`` alone where no sign makes sense)

NumPy only; nothing here is called inside ``jit``.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

_DECIMAL = rb"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?"
_NONFINITE = rb"[+-]?(?:[nN][aA][nN]|[iI][nN][fF](?:[iI][nN][iI][tT][yY])?)"
_NUMBER = rb"(?:" + _DECIMAL + rb"|" + _NONFINITE + rb")"

DECIMAL_RE = re.compile(_DECIMAL)
NUMBER_RE = re.compile(_NUMBER)
INTEGER_RE = re.compile(rb"[+-]?[0-9]+")
UNSIGNED_RE = re.compile(rb"[0-9]+")
# A whole space-joined token list at once: one regex call per line instead of one per token.
_NUMBER_LIST_RE = re.compile(_NUMBER + rb"(?: " + _NUMBER + rb")*")
_INTEGER_LIST_RE = re.compile(rb"[+-]?[0-9]+(?: [+-]?[0-9]+)*")

NUMBER_FORMAT = "decimal numbers such as 1, -2.5, .5, 3e-4 (or nan / inf)"


class NumberSyntaxError(ValueError):
    """A token is not a number of the accepted syntax.

    Attributes:
        index: Position of the offending token in the list given to :func:`parse_numbers`.
        token: The token, decoded as latin-1.
    """

    def __init__(self, index: int, token: bytes) -> None:
        self.index = index
        self.token = token.decode("latin-1")
        super().__init__(f"{self.token!r} is not a number")


def parse_numbers(tokens: Sequence[bytes]) -> list[float]:
    """Parses tokens that are decimal or non-finite numbers (see the module docstring).

    Callers reject ``nan``/``inf`` values afterwards where they make no sense; a decimal
    literal too large for float64 becomes ``inf`` and is caught by the same check.

    Raises:
        NumberSyntaxError: For the first token of any other syntax (``1_5``, ``0x1``, ``1e``).
    """
    if tokens and _NUMBER_LIST_RE.fullmatch(b" ".join(tokens)) is None:
        for i, token in enumerate(tokens):
            if NUMBER_RE.fullmatch(token) is None:
                raise NumberSyntaxError(i, token)
    return [float(t) for t in tokens]


def parse_integers(tokens: Sequence[bytes]) -> list[int]:
    """Parses ``[+-]? digits`` tokens into Python ints (range checks are the caller's).

    Raises:
        NumberSyntaxError: For the first token of any other syntax (``1_0``, ``7.0``, ``0x1``).
    """
    if tokens and _INTEGER_LIST_RE.fullmatch(b" ".join(tokens)) is None:
        for i, token in enumerate(tokens):
            if INTEGER_RE.fullmatch(token) is None:
                raise NumberSyntaxError(i, token)
    return [int(t) for t in tokens]


def parse_number(token: bytes) -> float:
    """One token through :func:`parse_numbers`."""
    return parse_numbers([token])[0]


def is_number(token: bytes) -> bool:
    """Whether ``token`` is a decimal or non-finite number."""
    return NUMBER_RE.fullmatch(token) is not None


def is_decimal(token: bytes) -> bool:
    """Whether ``token`` is a decimal literal (no nan / inf)."""
    return DECIMAL_RE.fullmatch(token) is not None


def is_integer(token: bytes, *, signed: bool = True) -> bool:
    """Whether ``token`` is ``[+-]? digits`` (``digits`` with ``signed=False``)."""
    return (INTEGER_RE if signed else UNSIGNED_RE).fullmatch(token) is not None
