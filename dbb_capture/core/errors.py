"""Typed errors: everything a user can fix is a :class:`DbbError`.

The command front ends catch it in one place, print its message as a single line
and exit with status 2; anything else is a bug and keeps its traceback.
"""


class DbbError(Exception):
    """Bad input or a condition the user can fix (message is one clear line)."""


class InputError(DbbError):
    """An input file or folder is missing, unreadable or malformed."""
