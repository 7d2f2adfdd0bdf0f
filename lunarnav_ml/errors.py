"""Errors the command line reports as one line (no traceback) with exit code 2."""


class LunarNavError(Exception):
    """Base class for user-facing errors: the message names the file, field or shape at fault."""


class InputError(LunarNavError):
    """Bad input: a missing or corrupt file, a malformed label, a wrong shape or a NaN."""


class ConfigError(LunarNavError):
    """A bad configuration: an unknown key or an impossible value."""


def one_line(err: BaseException) -> str:
    """An exception's message with its line breaks and runs of blanks collapsed (PyYAML's and
    PyTorch's messages span lines; a command line reports one)."""
    return " ".join(str(err).split())


# What a command line reports in one line: ours, a path that is missing or of the wrong kind,
# and one that cannot be written (a read-only folder, a folder wanted where a file is).
REPORTED_ERRORS = (LunarNavError, FileNotFoundError, NotADirectoryError, IsADirectoryError,
                   PermissionError, FileExistsError)
