"""Figures and tables of results."""

from rlbackdoors.report.curves import plot_training_curve

__all__ = ["plot_training_curve"]
