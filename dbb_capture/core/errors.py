"""Typed errors: everything a user can fix is a :class:`DbbError`.

The command front ends catch it in one place, print its message as a single line and exit
with status 2; anything else is a bug and keeps its traceback.

A message names the library's settings as ``{=name}`` (e.g. ``"{=crop_size} 48: expected
16..1024 pixels"``): read from the library it says ``crop_size``; a command front end words it
as its own option (``--crop-size``, :meth:`DbbError.worded`), so the library never assumes a
command line.
"""

from __future__ import annotations

import re
from collections.abc import Callable

_SETTING = re.compile(r"\{=([a-z_][a-z0-9_]*)\}")


class DbbError(Exception):
    """Bad input or a condition the user can fix (message is one clear line)."""

    def __str__(self) -> str:
        return self.worded(lambda name: name)

    def worded(self, word: Callable[[str], str]) -> str:
        """The message with each ``{=setting}`` replaced by ``word(setting)``."""
        msg = str(self.args[0]) if self.args else ""
        return _SETTING.sub(lambda m: word(m.group(1)), msg)


class InputError(DbbError):
    """An input file or folder is missing, unreadable or malformed."""
