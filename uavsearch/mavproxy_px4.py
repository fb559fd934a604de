"""A MAVProxy module: PX4 flight modes by name (`mode RTL`, `mode HOLD`, `rtl`, `hold`, ...).

Load it with MAVProxy's own module mechanism (MAVProxy itself stays as installed):

    mavproxy.py --master=udpin:127.0.0.1:14550 --load-module=uavsearch.mavproxy_px4

Why it is needed: MAVProxy 1.8.75's `mode NAME` (and `rtl`, and a mode name typed as a command) looks the
name up in pymavlink's PX4 table, whose entries are (base_mode, main, sub) tuples, and hands the tuple
to `mavfile.set_mode`; pymavlink 2.4.50's `set_mode_px4` unpacks only a *string*, so the tuple lands in
COMMAND_LONG's param1 and packing fails with "required argument is not a float". That happens inside the
ground station for every PX4 autopilot, before anything is sent, so no vehicle can answer it. pymavlink's
table also lacks PX4's HOLD and AUTO names. This module sends DO_SET_MODE with the autopilot's own mode
table (`uavsearch.flight.commander.PX4_MODES`), which is what QGroundControl and MAVSDK send.
"""

from __future__ import annotations

from MAVProxy.modules.lib import mp_module
from pymavlink import mavutil

from .flight.commander import PX4_MODES

M = mavutil.mavlink
# Other names users type for the same PX4 modes (pymavlink's, QGC's labels, PX4's AUTO_* names).
ALIASES = {"LOITER": "HOLD", "AUTO": "MISSION", "AUTO.MISSION": "MISSION", "AUTO.LOITER": "HOLD",
           "AUTO.RTL": "RTL", "AUTO.LAND": "LAND", "AUTO.TAKEOFF": "TAKEOFF", "POSITION": "POSCTL",
           "RETURN": "RTL"}
_AUTO_FLAGS = (M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | M.MAV_MODE_FLAG_AUTO_ENABLED | M.MAV_MODE_FLAG_GUIDED_ENABLED
               | M.MAV_MODE_FLAG_STABILIZE_ENABLED)


def px4_mode(name: str) -> tuple[int, int] | None:
    """(main, sub) for a PX4 mode name or alias, case-insensitive; None if unknown."""
    key = name.strip().upper()
    return PX4_MODES.get(ALIASES.get(key, key))


def mode_names() -> list[str]:
    return sorted(set(PX4_MODES) | set(ALIASES))


class PX4ModesModule(mp_module.MPModule):
    def __init__(self, mpstate):
        super().__init__(mpstate, "px4modes", "PX4 flight modes by name", public=True)
        self.commands = {"mode": (self.cmd_mode, "PX4 mode change"),
                         "rtl": (lambda args: self.set_mode("RTL"), "return to launch (PX4 Return mode)"),
                         "hold": (lambda args: self.set_mode("HOLD"), "hold position (PX4 Hold mode)")}
        self.add_completion_function("(PX4MODE)", lambda text: mode_names())
        self.claim_commands()

    def claim_commands(self):
        """(Re-)register our commands: MAVProxy loads --load-module modules before its default `mode` module,
        whose `mode` command would otherwise replace ours."""
        for name, (fn, text) in self.commands.items():
            if self.mpstate.command_map.get(name, (None,))[0] is not fn:
                self.add_command(name, fn, text, ["(PX4MODE)"] if name == "mode" else None)

    def idle_task(self):
        self.claim_commands()

    def cmd_mode(self, args):
        if len(args) != 1:
            print("Usage: mode " + "|".join(mode_names()))
            return
        self.set_mode(args[0])

    def set_mode(self, name: str) -> bool:
        ms = px4_mode(name)
        if ms is None:
            print(f"Unknown PX4 mode {name}; modes: {', '.join(mode_names())}")
            return False
        main, sub = ms
        base = _AUTO_FLAGS if main == PX4_MODES["MISSION"][0] else M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        self.master.mav.command_long_send(self.settings.target_system, self.settings.target_component,
                                          M.MAV_CMD_DO_SET_MODE, 0, base, main, sub, 0, 0, 0, 0)
        return True

    def unknown_command(self, args):
        """A mode name typed as a command (`RTL`, `HOLD`, `MISSION`), as MAVProxy allows for its own."""
        return bool(args) and px4_mode(args[0]) is not None and self.set_mode(args[0])


def init(mpstate):
    return PX4ModesModule(mpstate)
