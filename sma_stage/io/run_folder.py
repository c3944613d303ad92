"""A command's output files written as one set: the folder holds the files of one run, never a mix."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from types import TracebackType

from sma_stage.errors import InputError
from sma_stage.io.atomic import alive

MANIFEST = ".gpi_tool-run"  # the names of the files the last run wrote, one per line
STAGING_SUFFIX = ".staging"


class RunFolder:
    """Files of one run, written into a hidden staging folder beside `out` (`staging`) and moved into `out`
    when the block ends without an error; a run that fails or is interrupted leaves `out` as it was.
    Files an earlier run wrote there and this one does not are removed, so the folder holds one run's set.
    `out` is checked when the RunFolder is made, before any work: InputError with one line when it cannot
    be written."""

    def __init__(self, out: str | os.PathLike) -> None:
        self.out = Path(out)
        if self.out.is_symlink() and not self.out.exists():
            raise InputError(f"--out {self.out} is a symbolic link to nothing")
        if self.out.exists() and not self.out.is_dir():
            raise InputError(f"--out {self.out} is a file, not a folder")
        self._base = _nearest_folder(self.out.parent)
        try:
            sweep_stale_stagings(self._base)
            self.staging = Path(tempfile.mkdtemp(dir=self._base, prefix=f".{self.out.name}.{os.getpid()}.",
                                                 suffix=STAGING_SUFFIX))
        except OSError as error:
            raise InputError(f"--out {self.out} cannot be written: {error.strerror or error}") from None

    def __enter__(self) -> RunFolder:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> None:
        try:
            if kind is None:
                self._move_into_place()
            elif isinstance(error, OSError) and str(error.filename or "").startswith(str(self.staging)):
                name = Path(error.filename).relative_to(self.staging)
                raise OSError(error.errno, error.strerror, str(self.out / name)) from None
        finally:
            shutil.rmtree(self.staging, ignore_errors=True)

    def _move_into_place(self) -> None:
        try:
            self.out.mkdir(parents=True, exist_ok=True)
            written = sorted(path.name for path in self.staging.iterdir())
            for name in set(_manifest(self.out)) - set(written):
                (self.out / name).unlink(missing_ok=True)
            for name in written:
                os.replace(self.staging / name, self.out / name)
            (self.out / MANIFEST).write_text("".join(f"{name}\n" for name in written))
        except OSError as error:
            raise InputError(f"--out {self.out} cannot be written: {error.strerror or error}") from None


def _nearest_folder(folder: Path) -> Path:
    """folder, or its nearest ancestor that exists (the staging goes there: a failed run creates no folder)."""
    folder = folder.absolute()
    while not folder.exists() and folder.parent != folder:
        folder = folder.parent
    return folder


def sweep_stale_stagings(folder: Path) -> list[Path]:
    """Remove the staging folders of runs killed before they finished (`.<name>.<pid>.*.staging` of a process
    that no longer runs); the paths removed."""
    removed = []
    for candidate in folder.glob(f".*{STAGING_SUFFIX}"):
        parts = candidate.name.split(".")  # "", name (dots allowed), pid, random, "staging"
        pid = parts[-3] if len(parts) >= 5 else ""
        if pid.isdigit() and not alive(int(pid)) and candidate.is_dir() and not candidate.is_symlink():
            shutil.rmtree(candidate, ignore_errors=True)
            removed.append(candidate)
    return removed


def _manifest(folder: Path) -> list[str]:
    """The file names the last run wrote into folder (none without a manifest)."""
    try:
        names = (folder / MANIFEST).read_text().split("\n")
    except OSError:
        return []
    return [name for name in names if name and "/" not in name and name not in (".", "..")]
