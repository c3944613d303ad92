"""CSV data files with a header naming the columns t, input, output (or mapped names)."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from sma_stage.errors import InputError
from sma_stage.io.atomic import atomic_write_text
from sma_stage.io.series import DEFAULT_MIN_SAMPLES, Series, make_series

ROLES = ("t", "input", "output")
_DELIMITERS = (",", ";", "\t")


def _read_text(path: Path) -> str:
    if not path.exists():
        raise InputError(f"{path}: no such file or directory")
    try:
        return path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as error:
        raise InputError(f"{path}: not a UTF-8 text file ({error.reason} at byte {error.start})") from None
    except OSError as error:
        raise InputError(f"{path}: cannot read ({error.strerror})") from None


def _content_lines(text: str) -> list[tuple[int, str]]:
    """(line number, text) of the lines left after removing # comments and blank lines."""
    lines = ((number, raw.split("#", 1)[0].strip()) for number, raw in enumerate(text.splitlines(), 1))
    return [(number, line) for number, line in lines if line]


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


def _parse_header(lines: list[tuple[int, str]], path: Path) -> tuple[list[str], str | None]:
    if not lines:
        raise InputError(f"{path}: empty file (no header, no data)")
    number, line = lines[0]
    delimiter = _delimiter(line)
    header = _cells(line, delimiter)
    if all(_is_number(cell) for cell in header):
        raise InputError(f"{path}: line {number} is data, expected a header naming the columns t,input,output")
    duplicates = sorted({name for name in header if header.count(name) > 1})
    if duplicates:
        raise InputError(f"{path}: duplicate column name(s) in the header: {', '.join(_shown(name) for name in duplicates)}")
    return header, delimiter


def _split_rows(
    lines: list[tuple[int, str]], delimiter: str | None, width: int, path: Path
) -> list[list[str]]:
    rows = []
    for number, line in lines:
        cells = _cells(line, delimiter)
        if len(cells) != width:
            raise InputError(f"{path}: line {number} has {len(cells)} cells, the header has {width}")
        rows.append(cells)
    return rows


def _numeric_column(
    rows: list[list[str]], index: int, name: str, line_numbers: list[int], path: Path
) -> np.ndarray:
    texts = [row[index] for row in rows]
    try:
        values = np.array([_number(text) for text in texts], dtype=np.float64)
    except ValueError:
        bad = next(k for k, text in enumerate(texts) if not _is_number(text))
        raise InputError(
            f"{path}: line {line_numbers[bad]}, column '{name}': '{_shown(texts[bad])}' is not a number"
        ) from None
    bad_values = np.flatnonzero(~np.isfinite(values))
    if bad_values.size:
        k = int(bad_values[0])
        raise InputError(f"{path}: line {line_numbers[k]}, column '{name}': '{_shown(texts[k])}' is not finite")
    return values


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
    """
    path = Path(path)
    names = _role_names(columns)
    lines = _content_lines(_read_text(path))
    header, delimiter = _parse_header(lines, path)
    data_lines = lines[1:]
    if not data_lines:
        raise InputError(f"{path}: no data rows after the header")
    rows = _split_rows(data_lines, delimiter, len(header), path)
    numbers = [number for number, _ in data_lines]
    values = {
        role: _numeric_column(rows, _column_index(header, name, path), name, numbers, path)
        for role, name in names.items()
        if name is not None
    }
    t = values.get("t", np.arange(len(rows), dtype=np.float64))
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
