"""Benchmarks of soma_ros (run through ``soma bench ...`` or ``python -m benchmarks.<name>``)."""
