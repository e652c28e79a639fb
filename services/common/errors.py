"""The one error type for a mistake of the person running a command.

A :class:`UserError` names the thing that is wrong (a file, an option, a value) and how to fix
it, in one sentence. The ``handkse`` command prints it as one line and exits with status 2, with
no traceback unless ``--log-level DEBUG``. Library code raises it where the wrong value came
from the user (a path, an option), never for a bug or for bad bus input.
"""

from __future__ import annotations


class UserError(Exception):
    """A wrong file, option or value given by the user; the message says which and the fix."""
