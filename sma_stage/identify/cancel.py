"""Cooperative cancellation of an identification: the thread that runs a fit does it inside
`cancellable(event)`, and the fit's loops call `check_cancelled()`, which raises Cancelled once the event is
set (a node that is stopping sets it, so its refit ends within one iteration instead of running on).

Cancelled is a BaseException, as asyncio's CancelledError: the `except Exception` that keeps a plain fit
when the diagnosis fails does not swallow it."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar

_CANCEL: ContextVar[threading.Event | None] = ContextVar("sma_stage_cancel", default=None)


class Cancelled(BaseException):
    """The identification was cancelled before it finished (nothing was written)."""


@contextmanager
def cancellable(event: threading.Event) -> Iterator[None]:
    """Within the block (in this thread), check_cancelled() raises Cancelled once event is set."""
    token = _CANCEL.set(event)
    try:
        yield
    finally:
        _CANCEL.reset(token)


def cancel_requested() -> bool:
    """True when the enclosing cancellable() block's event is set."""
    event = _CANCEL.get()
    return event is not None and event.is_set()


def check_cancelled() -> None:
    """Raise Cancelled when the enclosing cancellable() block's event is set (nothing outside one)."""
    if cancel_requested():
        raise Cancelled("cancelled")


Progress = Callable[[str], None] | None  # where an identification reports what it is doing (None: nowhere)


def report(progress: Progress, message: str) -> None:
    """Raise Cancelled when cancelled (check_cancelled), else hand the message to progress (if any)."""
    check_cancelled()
    if progress is not None:
        progress(message)
