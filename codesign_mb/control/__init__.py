"""Ideal controllers: LQR/LQG for linear plants, MPC (CasADi), SAC (stable-baselines3)."""

from codesign_mb.control.base import Controller

__all__ = ["Controller"]
