"""Probes and analyses whose results the docs quote (the scripts in tools/ run them): they may build on every
other room, and nothing in the package builds on them, so a probe can change without touching the product."""
