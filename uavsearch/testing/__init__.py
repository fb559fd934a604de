"""Helpers the tests and the tools/ benchmarks share (a pymavlink test client, synthetic view caches), in
one importable place; nothing else in the package imports them."""
