"""The search loop shared by training, evaluation and flight: vehicles, perception, fusion, policies."""
