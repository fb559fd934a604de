"""Lockstep between `uavsearch sitl` and one MAVLink client: the simulation runs only while the client waits.

Why: a client in another process (the mission controller) spends wall time computing between commands.
A free-running vehicle keeps flying meanwhile, so each command lands at a different simulation instant
from run to run and a seed no longer fixes the flight. With lockstep the client hands out simulation
time explicitly and every command it sends is handled while the simulation stands still, so the same
seeds give the same flight however slow or busy the machine is (the idea of PX4 SITL's lockstep with
Gazebo, with the client as the clock master).

The protocol is one vendor command, MAV_CMD_SIM_ADVANCE (= MAV_CMD_USER_1, 31010), sent as
COMMAND_INT with `x` (or COMMAND_LONG with param5) = the simulation time, as time_boot_ms, to run to:

- the vehicle runs until its clock reaches that time (telemetry, events, physics as usual), then stops
  and answers COMMAND_ACK(ACCEPTED, result_param2 = its time_boot_ms). Every message it sent before
  the ACK precedes it on the link, so after the ACK the client has seen all of them;
- a time not ahead of the vehicle's clock is acknowledged at once: a barrier that costs no simulation
  time (the client calls it after a command to be sure the messages the command caused have arrived);
- the time is absolute, so a retransmitted grant is harmless;
- a vehicle started without `--lockstep` answers MAV_RESULT_UNSUPPORTED and keeps free-running.

While it stands still the vehicle keeps answering packets and sends a HEARTBEAT every wall second,
so that clients can find it before their first grant.
"""

from __future__ import annotations

from typing import Callable

MAV_CMD_SIM_ADVANCE = 31010  # MAV_CMD_USER_1
HOLD_HEARTBEAT_WALL_S = 1.0


class LockstepGate:
    """The vehicle side: how far the simulation may run, and whom to answer when it gets there."""

    def __init__(self) -> None:
        self.until_us = 0
        self._reply: Callable[[int], None] | None = None

    def grant(self, until_us: int, reply: Callable[[int], None]) -> None:
        """A grant to run until `until_us`; `reply(time_boot_ms)` is called once the clock is there (by the
        runner's hold, which also answers a grant that is not ahead of the clock, i.e. a barrier)."""
        self.until_us = max(self.until_us, until_us)
        self._reply = reply

    def arrived(self, now_us: int) -> None:
        if self._reply is not None:
            reply, self._reply = self._reply, None
            reply(int(now_us // 1000))
