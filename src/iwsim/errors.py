"""The errors ``iwsim`` reports to its user as one line (``cli.main`` catches these, and
OSError, and nothing else): everything else is a bug and shows its traceback."""


class IwsimError(Exception):
    """A failure that is not a bug: the message says what happened and what to do."""


class InputError(IwsimError, ValueError):
    """Bad input from a user (a file, flag, message or action), named in one sentence with
    what was expected. A ValueError too, as these always were."""
