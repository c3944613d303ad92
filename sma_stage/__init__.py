"""sma_stage: hysteresis modelling, compensation and identification for SMA micro-positioning stages."""

import os
from pathlib import Path

__version__ = "0.1.0"


def _numba_cache_dir() -> str:
    """Where the compiled kernels are cached: a user-writable folder, not the install tree (an /opt/ros install is
    read-only, and a build's tree should not change when the package runs)."""
    cache_home = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return str(Path(cache_home) / "sma_stage" / "numba")


os.environ.setdefault("NUMBA_CACHE_DIR", _numba_cache_dir())  # numba reads it when first imported
