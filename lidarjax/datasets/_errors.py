"""Exceptions raised by the dataset layer."""

from __future__ import annotations

import os


class DatasetFormatError(ValueError):
    """A data file is corrupt, truncated or not in the expected format.

    The message always quotes the path, the (1-based) line number where known, and the
    expected format, e.g. ``intel.log.gz:17: expected 'FLASER n r_1 .. r_n x y theta ...'``.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        message: str,
        *,
        line: int | None = None,
        expected: str | None = None,
    ) -> None:
        self.path = str(path)
        self.line = line
        self.expected = expected
        where = self.path if line is None else f"{self.path}:{line}"
        text = f"{where}: {message}"
        if expected:
            text += f" (expected: {expected})"
        super().__init__(text)


class DataNotFoundError(FileNotFoundError):
    """A registered data file is in none of the searched folders and cannot be downloaded."""


class DataChecksumError(ValueError):
    """A data file was found but its SHA-256 does not match the registry."""
