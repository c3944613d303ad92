"""A command's output files written as one set: the folder holds the files of one run, never a mix."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from types import TracebackType

from sma_stage.errors import InputError

MANIFEST = ".gpi_tool-run"  # the names of the files the last run wrote, one per line


class RunFolder:
    """Files of one run, written into a hidden staging folder beside `out` (`staging`) and moved into `out`
    when the block ends without an error; a run that fails or is interrupted leaves `out` as it was.
    Files an earlier run wrote there and this one does not are removed, so the folder holds one run's set.
    `out` is checked when the RunFolder is made, before any work: InputError with one line when it cannot
    be written."""

    def __init__(self, out: str | os.PathLike) -> None:
        self.out = Path(out)
        if self.out.exists() and not self.out.is_dir():
            raise InputError(f"--out {self.out} is a file, not a folder")
        try:
            self.out.parent.mkdir(parents=True, exist_ok=True)
            self.staging = Path(tempfile.mkdtemp(dir=self.out.parent, prefix=f".{self.out.name}.", suffix=".staging"))
        except OSError as error:
            raise InputError(f"--out {self.out} cannot be written: {error.strerror or error}") from None

    def __enter__(self) -> RunFolder:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> None:
        try:
            if kind is None:
                self._move_into_place()
        finally:
            shutil.rmtree(self.staging, ignore_errors=True)

    def _move_into_place(self) -> None:
        try:
            self.out.mkdir(exist_ok=True)
            written = sorted(path.name for path in self.staging.iterdir())
            for name in set(_manifest(self.out)) - set(written):
                (self.out / name).unlink(missing_ok=True)
            for name in written:
                os.replace(self.staging / name, self.out / name)
            (self.out / MANIFEST).write_text("".join(f"{name}\n" for name in written))
        except OSError as error:
            raise InputError(f"--out {self.out} cannot be written: {error.strerror or error}") from None


def _manifest(folder: Path) -> list[str]:
    """The file names the last run wrote into folder (none without a manifest)."""
    try:
        names = (folder / MANIFEST).read_text().split("\n")
    except OSError:
        return []
    return [name for name in names if name and "/" not in name and name not in (".", "..")]
