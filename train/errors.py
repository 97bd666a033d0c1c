"""The project's error type: every expected failure is a DdynError with a message a user can act on."""
from __future__ import annotations


class DdynError(Exception):
    """A user-facing error (bad input file, unknown vehicle, mismatched artefact...)."""


class CarLostError(DdynError):
    """A simulated plant's driver lost the car: it left the track, spun or the integration diverged. The plant and
    its inputs are sound; the driving was beyond that car's grip (a slower lap may well go round)."""


class DataError(DdynError):
    """Bad data in a file: names the file, and where known the row and column, and what was expected.

    Rows are 1-based line numbers of the file as a text editor shows them (for
    non-text formats, 1-based sample indices).
    """

    def __init__(self, path, message: str, row: int | None = None, column: str | None = None):
        self.path, self.row, self.column, self.detail = str(path), row, column, message
        where = self.path
        if row is not None:
            where += f", row {row}"
        if column is not None:
            where += f", column {column!r}"
        super().__init__(f"{where}: {message}")
