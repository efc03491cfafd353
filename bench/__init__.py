"""Benchmarks of ctid_ros (run with ``make bench``); not part of ``make test``."""
