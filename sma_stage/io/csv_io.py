"""CSV data files with a header naming the columns t, input, output (or mapped names)."""

from __future__ import annotations

import math
import os
from array import array
from collections import Counter
from collections.abc import Iterator, Mapping
from itertools import chain
from pathlib import Path
from typing import TextIO

import numpy as np

from sma_stage.errors import InputError
from sma_stage.io.atomic import atomic_write_text
from sma_stage.io.series import DEFAULT_MIN_SAMPLES, Series, make_series

ROLES = ("t", "input", "output")
_DELIMITERS = (",", ";", "\t")


MAX_HEADER_CHARACTERS = 10_000_000


class _SlowPath(Exception):
    """The fast reader met something it does not read as the strict reader would: read again, slowly."""


def _open(path: Path) -> TextIO:
    """The file as UTF-8 text (a byte-order mark dropped); InputError for what is not a readable regular file."""
    if not path.exists() and not path.is_symlink():
        raise InputError(f"{path}: no such file or directory")
    if not path.is_file():
        raise InputError(f"{path}: not a regular file")
    try:
        return open(path, encoding="utf-8-sig", newline=None)
    except OSError as error:
        raise InputError(f"{path}: cannot read ({error.strerror})") from None


def _content(raw: str) -> str:
    """A line without its # comment and surrounding blanks."""
    return raw.split("#", 1)[0].strip() if "#" in raw else raw.strip()


def _lines(file: TextIO, path: Path, first_number: int = 1) -> Iterator[tuple[int, str]]:
    """(line number, content) of the non-blank lines after removing # comments; InputError for bytes that are not
    UTF-8."""
    number = first_number - 1
    try:
        for raw in file:
            number += 1
            line = _content(raw)
            if line:
                yield number, line
    except UnicodeDecodeError as error:
        raise InputError(f"{path}: not a UTF-8 text file ({error.reason} near line {number + 1})") from None
    except OSError as error:
        raise InputError(f"{path}: cannot read ({error.strerror})") from None


def _delimiter(header: str) -> str | None:
    return next((d for d in _DELIMITERS if d in header), None)


def _cells(line: str, delimiter: str | None) -> list[str]:
    return [cell.strip().strip('"').strip("'").strip() for cell in line.split(delimiter)]


def _number(text: str) -> float:
    """The cell as a float; ValueError for anything but a plain decimal number (Python's float() would
    also take '1_0' as 10)."""
    if "_" in text:
        raise ValueError(text)
    return float(text)


def _is_number(text: str) -> bool:
    try:
        _number(text)
    except ValueError:
        return False
    return True


def _shown(text: str, limit: int = 40) -> str:
    """A cell as an error message quotes it: at most `limit` characters and its length."""
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text):,} characters)"


def _role_names(columns: Mapping[str, str | None] | None) -> dict[str, str | None]:
    names: dict[str, str | None] = {role: role for role in ROLES}
    unknown = sorted(set(columns or {}) - set(ROLES))
    if unknown:
        raise InputError(f"unknown column role(s) {', '.join(unknown)}; the roles are t, input, output")
    names.update(columns or {})
    if names["input"] is None or names["output"] is None:
        raise InputError("the input and output columns must be named (only t may be None)")
    return names


def _column_index(header: list[str], name: str, path: Path) -> int:
    if name in header:
        return header.index(name)
    folded = [i for i, found in enumerate(header) if found.casefold() == name.casefold()]
    if len(folded) == 1:
        return folded[0]
    raise InputError(f"{path}: no column '{name}' (columns found: {', '.join(_shown(found) for found in header[:20])}"
                     + (f" and {len(header) - 20} more)" if len(header) > 20 else ")"))


def _read_header(path: Path) -> tuple[int, list[str], str | None]:
    """(line number, column names, delimiter) of the header: the first line with content."""
    with _open(path) as file:
        number = 0
        while True:
            try:
                raw = file.readline(MAX_HEADER_CHARACTERS + 1)
            except UnicodeDecodeError as error:
                raise InputError(f"{path}: not a UTF-8 text file ({error.reason} near line {number + 1})") from None
            if not raw:
                raise InputError(f"{path}: empty file (no header, no data)")
            number += 1
            if len(raw) > MAX_HEADER_CHARACTERS:
                raise InputError(f"{path}: line {number} is longer than {MAX_HEADER_CHARACTERS:,} characters: "
                                 "not a header of columns t,input,output")
            line = _content(raw)
            if line:
                break
    delimiter = _delimiter(line)
    header = _cells(line, delimiter)
    if all(_is_number(cell) for cell in header):
        raise InputError(f"{path}: line {number} is data, expected a header naming the columns t,input,output")
    duplicates = sorted(name for name, count in Counter(header).items() if count > 1)
    if duplicates:
        raise InputError(f"{path}: duplicate column name(s) in the header: {', '.join(_shown(name) for name in duplicates)}")
    return number, header, delimiter


def _data_lines(path: Path, header_number: int) -> Iterator[tuple[int, str]]:
    """The content lines after the header."""
    with _open(path) as file:
        for _ in range(header_number):
            file.readline()
        yield from _lines(file, path, header_number + 1)


def _fast_columns(path: Path, header_number: int, delimiter: str | None, width: int,
                  indices: list[int]) -> np.ndarray:
    """The role columns (rows x len(indices)) through numpy's parser; _SlowPath when a line is not as plain as
    the strict reader wants it (another width, a quote, a cell numpy reads differently, a non-finite value)."""
    def checked() -> Iterator[str]:
        separators = width - 1
        for _, line in _data_lines(path, header_number):
            count = len(line.split()) - 1 if delimiter is None else line.count(delimiter)
            if count != separators or "'" in line or "_" in line:
                raise _SlowPath
            yield line

    lines = checked()
    first = next(lines, None)
    if first is None:
        return np.empty((0, len(indices)))
    try:
        values = np.loadtxt(chain([first], lines), delimiter=delimiter, comments=None, usecols=indices,
                            dtype=np.float64, ndmin=2, quotechar='"')
    except ValueError:
        raise _SlowPath from None
    if not np.all(np.isfinite(values)):
        raise _SlowPath
    return values


def _strict_columns(path: Path, header_number: int, delimiter: str | None, width: int,
                    roles: dict[str, int], names: dict[str, str]) -> dict[str, np.ndarray]:
    """The role columns, line by line: the first line that is not as wanted is named in an InputError."""
    columns = {role: array("d") for role in roles}
    for number, line in _data_lines(path, header_number):
        cells = _cells(line, delimiter)
        if len(cells) != width:
            raise InputError(f"{path}: line {number} has {len(cells)} cells, the header has {width}")
        for role, index in roles.items():
            text = cells[index]
            try:
                value = _number(text)
            except ValueError:
                raise InputError(f"{path}: line {number}, column '{names[role]}': '{_shown(text)}' is not a "
                                 "number") from None
            if not math.isfinite(value):
                raise InputError(f"{path}: line {number}, column '{names[role]}': '{_shown(text)}' is not finite")
            columns[role].append(value)
    return {role: np.frombuffer(values, dtype=np.float64) for role, values in columns.items()}


def _looks_like_index(t: np.ndarray) -> bool:
    return len(t) > 1 and bool(np.all(t == np.round(t))) and bool(np.all(np.diff(t) == 1.0))


def read_csv(
    path: str | os.PathLike,
    columns: Mapping[str, str | None] | None = None,
    min_samples: int = DEFAULT_MIN_SAMPLES,
) -> Series:
    """Read a CSV file into a checked Series.

    `columns` maps roles to header names, e.g. {"t": "time", "input": "current", "output": "pos"};
    {"t": None} uses the sample index as time. Lines starting with # and blank lines are ignored.
    Time counts as a sample index when t is mapped to None or holds consecutive integers.
    Memory: the three columns as float64 (24 MB per million rows) and numpy's parsing buffers.
    """
    path = Path(path)
    names = _role_names(columns)
    header_number, header, delimiter = _read_header(path)
    roles = {role: _column_index(header, name, path) for role, name in names.items() if name is not None}
    try:
        block = _fast_columns(path, header_number, delimiter, len(header), list(roles.values()))
        values = {role: np.ascontiguousarray(block[:, k]) for k, role in enumerate(roles)}
    except _SlowPath:
        values = _strict_columns(path, header_number, delimiter, len(header), roles, names)
    rows = next(iter(values.values())).size
    if rows == 0:
        raise InputError(f"{path}: no data rows after the header")
    t = values.get("t", np.arange(rows, dtype=np.float64))
    time_is_index = names["t"] is None or _looks_like_index(t)
    return make_series(t, values["input"], values["output"], str(path), time_is_index, min_samples)


def write_csv(path: str | os.PathLike, series: Series, comment: str | None = None) -> None:
    """Write series atomically as CSV with the header t,input,output and round-trip float precision.

    An optional comment is written first as # lines.
    """
    preamble = "".join(f"# {line}\n" for line in comment.splitlines()) if comment else ""
    body = "\n".join(
        f"{t!r},{u!r},{y!r}"
        for t, u, y in zip(series.t.tolist(), series.input.tolist(), series.output.tolist(), strict=True)
    )
    atomic_write_text(path, f"{preamble}t,input,output\n{body}\n")
