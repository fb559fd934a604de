"""The vehicle's MAVLink side split by capability, as MAVSDK splits plugins, plus the client-side wire units.

`endpoint.MavlinkEndpoint` composes links, streams, commands, params, mission, camera and offboard; each
module serves one protocol. `wire_units` is the one decoding of wire units that clients (the mission
controller, replay) share. Nothing is imported here, so a client that needs only `wire_units` does not
load the vehicle side.
"""
