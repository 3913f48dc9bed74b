"""Benchmarks of whole loops (controller, estimator, link and records on top of the env)."""
