"""Evaluation: Table I (single view), Table II (search), perception targets and the bounds; never imports train."""
