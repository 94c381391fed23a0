"""Exception types whose message is meant for the user (the CLI prints them without a traceback)."""


class SssError(Exception):
    """Base class: an error with a message that names the problem and what to do about it."""


class InputError(SssError, ValueError):
    """Bad user input: wrong shape, unknown name, out-of-range value."""


class UnknownObjectError(InputError):
    """An object name that is not in the simulator's catalogue."""


class DataError(SssError):
    """Stored data that is missing, corrupt or inconsistent."""
