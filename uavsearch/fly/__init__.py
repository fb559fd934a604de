"""Flying the search loop over MAVLink: the client, the mission controller, mission files, upload, .plan files."""
