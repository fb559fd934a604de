"""User-facing errors: the CLI prints these as one line, never a traceback."""


class UavsearchError(Exception):
    """Bad input or an impossible request; the message is the one line the user sees."""


class SceneError(UavsearchError):
    """An unknown, malformed or impossible scene (bad seed, K out of range, corrupt JSON)."""


class MissionError(UavsearchError):
    """A mission file that does not validate."""


class LogError(UavsearchError):
    """A flight log that cannot be read."""
