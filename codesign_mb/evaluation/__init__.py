"""Rollouts, metrics, tables, plots and sweeps."""

from codesign_mb.evaluation.rollout import rollout

__all__ = ["rollout"]
