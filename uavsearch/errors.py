"""User-facing errors: the CLI prints these as one line, never a traceback."""

import sys


class UavsearchError(Exception):
    """Bad input or an impossible request; the message is the one line the user sees."""


class SceneError(UavsearchError):
    """An unknown, malformed or impossible scene (bad seed, K out of range, corrupt JSON)."""


class MissionError(UavsearchError):
    """A mission file that does not validate."""


class LogError(UavsearchError):
    """A flight log that cannot be read."""


def run_command(func, args, prog: str = "uavsearch") -> int:
    """Run a subcommand handler; a UavsearchError becomes one line on stderr and exit 2, Ctrl-C exit 130."""
    try:
        return int(func(args) or 0)
    except UavsearchError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
