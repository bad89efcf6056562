"""The project's own error for input it cannot use, and the guard every file reader runs under.

A reader either returns a valid result or raises :class:`InputError`, whose message names the
file, the field or line at fault where there is one, and what to do. It is a ``ValueError``, so
callers (and the command line, which prints it as one line with exit code 2) treat it as a bad
value. A missing or unreadable file stays the operating system's error (``FileNotFoundError``,
``PermissionError``): it names the path, and nothing in the file was read.
"""

from __future__ import annotations

import contextlib
from pathlib import Path


class InputError(ValueError):
    """A file, or a value in one, that the project cannot use; the message says which, what is
    wrong and what to do."""


def one_line(error: BaseException) -> str:
    """One line for an exception raised inside a library (json, numpy, VTK, SimpleITK, XML)."""
    lines = [line.strip() for line in str(error).strip().splitlines() if line.strip()]
    text = lines[-1] if lines else ""
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


@contextlib.contextmanager
def reading(path: str | Path, what: str, remedy: str):
    """Run a reader's body: an :class:`InputError` passes as it is; a ``ValueError`` whose message
    already names the file becomes an InputError with that message; any other error raised while
    the file's content is interpreted (a KeyError of a missing field, a TypeError of a value of the
    wrong kind, a library's own exception) becomes an InputError "PATH: not a usable WHAT (the
    error); REMEDY". Operating-system errors (a missing or unreadable file) pass unchanged."""
    try:
        yield
    except (InputError, OSError):
        raise
    except ValueError as error:
        if str(path) in str(error):
            raise InputError(str(error)) from error
        raise InputError(f"{path}: not a usable {what} ({one_line(error)}); {remedy}") from error
    except (LookupError, TypeError, AttributeError, ArithmeticError, RuntimeError,
            SyntaxError) as error:  # SyntaxError: xml.etree's ParseError
        raise InputError(f"{path}: not a usable {what} ({one_line(error)}); {remedy}") from error
