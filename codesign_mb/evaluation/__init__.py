"""Seeded parallel evaluation (one process pool, local or Ray) and its summaries."""
