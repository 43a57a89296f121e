"""The library's errors for bad input or a bad environment: one line each, never a traceback at the CLI.

Library code raises `StgsError` (or a subclass) and names what is wrong in
its own terms: a config field, a file, a manifest element. `FieldError`
carries the config field's name so that a front end can speak of its own
controls instead (the CLI maps fields to flags); the library never speaks of
command-line flags.
"""


class StgsError(Exception):
    """Bad input or environment: the CLI prints `stgs: <message>` and exits non-zero."""


class FieldError(StgsError):
    """A configuration value that is invalid; `field` names it (a dataclass field of the config)."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field, self.message = field, message


class NativeUnavailableError(RuntimeError):
    """The native kernels could not be built or loaded (the pure-torch reference runs instead, where there is one)."""


class MPDError(ValueError):
    """A manifest that is not well-formed or not what this profile expects."""
