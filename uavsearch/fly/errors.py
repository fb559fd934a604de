"""The client's typed failures: what went wrong, and for a command, which command and what the vehicle said."""

from __future__ import annotations

from ..errors import UavsearchError


class FlightError(UavsearchError):
    """The vehicle could not do what the mission asked (no link, arming refused, a step timed out)."""


class StepFailed(FlightError):
    """One capture step failed cleanly (not arrived in time, camera did not answer); the vehicle is still flying."""


class CommandError(FlightError):
    """A command the vehicle refused or never acknowledged: `command` (MAV_CMD number), `result` (MAV_RESULT,
    None when no COMMAND_ACK came)."""

    def __init__(self, message: str, command: int, result: int | None):
        super().__init__(message)
        self.command, self.result = command, result


class VehicleDown(StepFailed):
    """The vehicle cannot go on with the search (disarmed, a failsafe mode it was not asked for, battery critical,
    no progress to its goal, its link gone): the reason names what it did; its process still runs."""


class VehicleLost(FlightError):
    """The vehicle process this client started has exited (its exit status says how)."""
