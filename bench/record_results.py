"""What a benchmark prints, also written to bench/results/<name>.md: the command and the date first, the output
in a code block. The file is replaced atomically when the run ends normally; a failed or interrupted run leaves
the last one in place."""

from __future__ import annotations

import datetime
import io
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


class _Tee(io.TextIOBase):
    """A text stream writing to the terminal and keeping a copy."""

    def __init__(self, terminal: io.TextIOBase) -> None:
        self.terminal, self.copy = terminal, io.StringIO()

    def write(self, text: str) -> int:
        self.copy.write(text)
        return self.terminal.write(text)

    def flush(self) -> None:
        self.terminal.flush()


def machine() -> str:
    """The CPUs a run had, with their model where Linux names it ("2 CPUs, AMD EPYC"): figures that are the same
    from run to run on one machine may differ on another CPU, whose compiled code and BLAS round differently."""
    try:
        with open("/proc/cpuinfo") as info:
            model = next((line.split(":", 1)[1].strip() for line in info if line.startswith("model name")), "")
    except OSError:
        model = ""
    return f"{os.cpu_count()} CPUs" + (f", {model}" if model else "")


def results_path(script: str, name: str | None = None) -> Path:
    """bench/results/<name>.md, by default the script's name without bench_."""
    return RESULTS / f"{name or Path(script).stem.removeprefix('bench_')}.md"


@contextmanager
def recorded(script: str, name: str | None = None) -> Iterator[None]:
    """Within the block, stdout also goes to results_path(script, name), written when the block ends without an
    error (a SystemExit with status 0 or None counts as without)."""
    tee, terminal = _Tee(sys.stdout), sys.stdout
    sys.stdout = tee
    started = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    try:
        yield
    except SystemExit as leaving:
        if leaving.code not in (None, 0):
            raise
        _write(script, name, started, tee.copy.getvalue())
        raise
    else:
        _write(script, name, started, tee.copy.getvalue())
    finally:
        sys.stdout = terminal


def _write(script: str, name: str | None, started: str, output: str) -> None:
    path = results_path(script, name)
    command = " ".join([".venv/bin/python", f"bench/{Path(script).name}", *sys.argv[1:]])
    text = f"# {Path(script).name}\n\n`{command}` ({started}, {machine()})\n\n```\n{output.rstrip()}\n```\n"
    path.parent.mkdir(exist_ok=True)
    staging = path.with_suffix(".md.tmp")
    staging.write_text(text)
    os.replace(staging, path)
