"""Atomic file writes: a reader sees the old file or the new one, never half of either."""

import os
import stat
import tempfile
import time
from pathlib import Path


def _umask() -> int:
    """The process's file-mode creation mask (read from /proc on Linux; else set and restored at once)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _mode_for(target: Path) -> int:
    """The permission bits the written file gets: those of the file it replaces, else 0666 less the umask (as
    open() would give a new file; a temporary file alone would be 0600 whatever the umask)."""
    try:
        return stat.S_IMODE(target.stat().st_mode)
    except FileNotFoundError:
        return 0o666 & ~_umask()


def alive(pid: int) -> bool:
    """True when a process of this pid runs on this machine (or may: one of another user)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


STALE_TEMPORARY_S = 10.0  # a temporary this old, of a writer that no longer runs, is a killed write's leftover


def sweep_stale_temporaries(target: Path) -> list[Path]:
    """Remove the hidden temporaries that earlier writes of target left when killed (`.<name>.<pid>.*.tmp` of a
    process that no longer runs, at least STALE_TEMPORARY_S old); the paths removed."""
    removed = []
    for candidate in target.parent.glob(f".{target.name}.*.tmp"):
        pid = candidate.name[len(target.name) + 2:].split(".", 1)[0]
        try:
            stale = not alive(int(pid)) and time.time() - candidate.stat().st_mtime >= STALE_TEMPORARY_S
        except (ValueError, OSError):
            continue
        if stale:
            candidate.unlink(missing_ok=True)
            removed.append(candidate)
    return removed


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write data to path through a temporary file in the same folder and an atomic rename; an OSError names
    path, never the temporary file. Temporaries that killed writes of path left behind are removed."""
    target = Path(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        sweep_stale_temporaries(target)
        handle, temporary = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.{os.getpid()}.",
                                             suffix=".tmp")
    except OSError as error:
        raise OSError(error.errno, error.strerror, str(target)) from None
    try:
        with os.fdopen(handle, "wb") as stream:
            os.fchmod(stream.fileno(), _mode_for(target))
            stream.write(data)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, target)
    except OSError as error:
        Path(temporary).unlink(missing_ok=True)
        raise OSError(error.errno, error.strerror, str(target)) from None
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write text (UTF-8) to path atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))
