"""Benchmarks (env, closed loop, MPC, allocators): each prints its figures as JSON."""
