"""Errors that mean "the user asked for something wrong", reported as one line without a traceback."""


class UserError(Exception):
    """Bad input or environment: the CLI prints `stgs: <message>` and exits non-zero."""
