"""The one error type for bad user input: its message is a single line a user can act on."""


class InputError(ValueError):
    """Bad input (a NaN, a missing column, an out-of-range parameter, no excitation, ...)."""

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))
