"""Files and YAML a user hands the package (model files, the compensator's `model` text, hardware files, data
files), read so that none can take a node or the command line down: regular files only (a FIFO or a device
would block or never end), bounded size and nesting, no aliases, text keys, integers that fit a float. Any
problem is one InputError line."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import yaml

from sma_stage.errors import InputError

MAX_YAML_BYTES = 1 << 20  # a model file is about 2 kB, a hardware file about 4 kB
MAX_YAML_DEPTH = 32  # the deepest shipped file nests 4 levels
_OPENING = (yaml.MappingStartEvent, yaml.SequenceStartEvent)
_CLOSING = (yaml.MappingEndEvent, yaml.SequenceEndEvent)


def regular_file(path: str | os.PathLike, what: str) -> os.stat_result:
    """The stat of path, a regular file (symlinks followed); InputError naming `what` otherwise."""
    try:
        status = os.stat(path)
    except FileNotFoundError:
        raise InputError(f"{what} not found: {path}") from None
    except OSError as error:
        raise InputError(f"cannot read {what} {path}: {error.strerror or error}") from None
    if not stat.S_ISREG(status.st_mode):
        raise InputError(f"{what} {path} is not a regular file")
    return status


def read_text_file(path: str | os.PathLike, what: str, max_bytes: int = MAX_YAML_BYTES) -> str:
    """The UTF-8 text of a regular file of at most max_bytes; InputError naming `what` otherwise."""
    size = regular_file(path, what).st_size
    if size > max_bytes:
        raise InputError(f"{what} {path} is {size:,} bytes: more than the {max_bytes:,} such a file can be")
    try:
        with open(path, "rb") as file:
            data = file.read(max_bytes + 1)
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise InputError(f"{what} {path} is not UTF-8 text ({error.reason} at byte {error.start})") from None
    except OSError as error:
        raise InputError(f"cannot read {what} {path}: {error.strerror or error}") from None


def parse_yaml(text: str, max_bytes: int = MAX_YAML_BYTES) -> object:
    """The document in text (safe types only), checked: at most max_bytes characters and MAX_YAML_DEPTH levels,
    no aliases, text keys, integers a float can hold; InputError in one line otherwise."""
    if len(text) > max_bytes:
        raise InputError(f"YAML text of {len(text):,} characters: more than the {max_bytes:,} accepted")
    try:
        _check_events(text)
        document = yaml.safe_load(text)
    except yaml.YAMLError as error:
        first_line = str(error).splitlines()[0] if str(error) else "invalid YAML"
        raise InputError(f"not valid YAML: {first_line}") from None
    except (ValueError, OverflowError, TypeError) as error:  # a constructor's (e.g. a date out of range)
        raise InputError(f"not valid YAML: {' '.join(str(error).split())[:200]}") from None
    _check_values(document)
    return document


def load_yaml_file(path: str | os.PathLike, what: str) -> object:
    """parse_yaml of a regular file's text; the InputError names the file."""
    text = read_text_file(path, what)
    try:
        return parse_yaml(text)
    except InputError as error:
        raise InputError(f"{what} {Path(path)}: {error}") from None


def _check_events(text: str) -> None:
    """Refuse aliases and nesting beyond MAX_YAML_DEPTH from the event stream (iterative: the composer that
    builds the document recurses, and a deep file would exhaust its stack)."""
    depth = 0
    for event in yaml.parse(text, Loader=yaml.SafeLoader):
        if isinstance(event, _OPENING):
            depth += 1
            if depth > MAX_YAML_DEPTH:
                raise InputError(f"nested more than {MAX_YAML_DEPTH} levels deep")
        elif isinstance(event, _CLOSING):
            depth -= 1
        elif isinstance(event, yaml.AliasEvent):
            raise InputError(f"aliases (*{event.anchor}) are not accepted")


def _check_values(document: object) -> None:
    pending = [document]
    while pending:
        value = pending.pop()
        if isinstance(value, dict):
            for key, item in value.items():
                if not isinstance(key, str):
                    raise InputError(f"key {_shown(key)} is not text (keys are names)")
                pending.append(item)
        elif isinstance(value, list):
            pending.extend(value)
        elif isinstance(value, int) and not isinstance(value, bool):
            try:
                float(value)
            except OverflowError:
                raise InputError(f"the number {_shown(value)} is too large for a float") from None


def _shown(value: object, limit: int = 40) -> str:
    text = repr(value) if not isinstance(value, int) else str(value)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text):,} characters)"
