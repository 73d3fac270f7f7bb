"""Honest evaluation: clean and triggered success rates and rewards."""

from rlbackdoors.evaluate.episodes import EvalResult, evaluate, play_episodes

__all__ = ["EvalResult", "evaluate", "play_episodes"]
