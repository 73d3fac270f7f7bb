"""Honest evaluation: clean and triggered success rates and rewards."""

from rlbackdoors.evaluate.episodes import EvalResult, evaluate, play_episodes, score_triggered

__all__ = ["EvalResult", "evaluate", "play_episodes", "score_triggered"]
