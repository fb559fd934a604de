"""Replaying flight logs: re-scoring, plots and video, and the flight review page."""
