"""User-facing errors: the CLI prints these as one line, never a traceback."""

import signal
import sys
import threading
from contextlib import contextmanager


class UavsearchError(Exception):
    """Bad input or an impossible request; the message is the one line the user sees."""


class SceneError(UavsearchError):
    """An unknown, malformed or impossible scene (bad seed, K out of range, corrupt JSON)."""


class MissionError(UavsearchError):
    """A mission file that does not validate."""


class LogError(UavsearchError):
    """A flight log that cannot be read."""


def format_validation_error(e, source: str, kind: str = "mission") -> str:
    """pydantic's first error as one line: '<kind> <source>: <field>: <problem> (got <value>)'."""
    err = e.errors()[0]
    # a key of the user's file may hold a line break: shown as repr, the error stays one line
    loc = ".".join(str(x) if str(x).isprintable() else repr(x) for x in err.get("loc", ())
                   if not str(x).startswith("function-after"))
    msg = " ".join(err.get("msg", "invalid").splitlines())
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, "):]
    got = err.get("input")
    where = f"{loc}: " if loc else ""
    tail = f" (got {got!r})" if err.get("type") not in ("missing", "extra_forbidden", "value_error") and \
        not isinstance(got, (dict, list)) else ""
    if err.get("type") == "extra_forbidden":
        msg = "unknown field"
    more = f" [+{len(e.errors()) - 1} more]" if len(e.errors()) > 1 else ""
    return f"{kind} {source}: {where}{msg}{tail}{more}"


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


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the main thread is, so a command that ends cleanly on Ctrl-C ends so on it too."""

    def __str__(self) -> str:
        return "SIGTERM"


@contextmanager
def sigterm_as_interrupt():
    """Within: SIGTERM raises Terminated (a KeyboardInterrupt) in the main thread, so `fly` lands and writes its
    summary as on Ctrl-C; a second raises it again (a second Ctrl-C abandons the landing and ends at once), and a
    third is the default (the process dies). The handler before comes back on leaving. Commands set it, never
    an import, and only the main thread can: elsewhere nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received = 0

    def on_sigterm(signum, frame):
        nonlocal received
        received += 1
        if received >= 2:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
        raise Terminated()

    before = signal.signal(signal.SIGTERM, on_sigterm)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL if before is None else before)  # None: set outside Python
