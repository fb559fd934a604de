"""The client side of lockstep: this client is the vehicle's clock master (MAV_CMD_SIM_ADVANCE grants).

The vehicle (`uavsearch sitl --lockstep`) runs only as far as it is granted, answering each grant with
the time it stands at; every command is then sent while the simulation stands still, so perception and
policy take no simulation time and the same seeds fly the same flight. A free-running vehicle answers
UNSUPPORTED and the client stays free-running.
"""

from __future__ import annotations

from ..flight.lockstep import MAV_CMD_SIM_ADVANCE
from .dialect import M


class Lockstep:
    def __init__(self, system, tick_s: float = 0.1):
        self.system = system
        self.tick_s = tick_s  # simulation time per grant: conditions are judged at this spacing
        self.enabled = False  # on once the vehicle accepted a grant
        self.clock_ms = 0  # where the vehicle's clock stands (its answer to the last grant)

    def grant(self, until_ms: int) -> int:
        """MAV_CMD_SIM_ADVANCE to until_ms; returns the MAV_RESULT (UNSUPPORTED: a free-running vehicle)."""
        cmds = self.system.commands
        r = cmds.int(MAV_CMD_SIM_ADVANCE, M.MAV_FRAME_MISSION, 0, 0, 0, 0, int(until_ms), 0, 0.0)
        if r == M.MAV_RESULT_ACCEPTED:
            self.clock_ms = int(cmds.last_ack.result_param2)
        return r

    def start(self, tick_s: float | None = None) -> bool:
        """Take the clock (a grant to 0); False when the vehicle runs free."""
        if tick_s is not None:
            self.tick_s = tick_s
        self.enabled = self.grant(0) == M.MAV_RESULT_ACCEPTED
        return self.enabled

    def barrier(self) -> None:
        """A grant of no time: what the vehicle sent so far has arrived."""
        self.grant(self.clock_ms)

    def advance(self, sim_s: float | None = None) -> None:
        """Grant sim_s (default tick_s) more simulation time and wait for the vehicle to stand there."""
        self.grant(self.clock_ms + int(round(1000 * (sim_s or self.tick_s))))


__all__ = ["Lockstep", "MAV_CMD_SIM_ADVANCE"]
