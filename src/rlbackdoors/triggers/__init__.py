"""Trigger specifications and their insertion into observations or layouts."""

from rlbackdoors.triggers.observation import KINDS, PAPER_RANGES, ObservationTrigger, sample_trigger


__all__ = ["KINDS", "PAPER_RANGES", "ObservationTrigger", "sample_trigger"]
