"""Errors the command line reports as one line (no traceback) with exit code 2."""


class LunarNavError(Exception):
    """Base class for user-facing errors: the message names the file, field or shape at fault."""


class InputError(LunarNavError):
    """Bad input: a missing or corrupt file, a malformed label, a wrong shape or a NaN."""


class ConfigError(LunarNavError):
    """A bad configuration: an unknown key or an impossible value."""
