"""The one error type for bad user input: its message is a single line a user can act on."""

import math


class InputError(ValueError):
    """Bad input (a NaN, a missing column, an out-of-range parameter, no excitation, ...)."""

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))


def finite_number(name: str, value: object) -> float:
    """value as a float; InputError naming `name` unless it is a finite number."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise InputError(f"{name} must be finite, got {value!r}")
    return number


def non_negative_number(name: str, value: object) -> float:
    """value as a float; InputError naming `name` unless it is a finite number >= 0."""
    number = finite_number(name, value)
    if number < 0.0:
        raise InputError(f"{name} must be at least 0, got {value!r}")
    return number
