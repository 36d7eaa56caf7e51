"""The command line's own error type, apart from its parser so every command module can raise it."""


class UserError(Exception):
    """An error caused by the user's input; printed as one line without a traceback."""
