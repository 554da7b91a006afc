"""Errors the ``iwsim`` command reports as one line (besides ValueError and OSError)."""


class IwsimError(Exception):
    """A failure that is not a bug: the message says what happened and what to do."""
