"""uavsearch: a flight-dynamics-realistic MAVLink UAV testbed for active object search."""

__version__ = "0.1.0"
