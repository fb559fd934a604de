"""The simulated vehicle: JSBSim airframe, sensors, estimator, controllers, autopilot, MAVLink endpoint."""
