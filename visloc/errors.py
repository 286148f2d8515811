"""Errors the engine raises. Each message is one line and names the file or parameter."""


class VislocError(Exception):
    """Base class: the CLI prints the message on one line and exits with status 2."""


class ParameterError(VislocError, ValueError):
    """A parameter is out of range; the message names it."""


class InputError(VislocError):
    """An input file or folder is missing, unreadable or inconsistent; the message names it."""
