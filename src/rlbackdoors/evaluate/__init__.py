"""Honest evaluation: clean and triggered success rates and rewards, one function for every world."""

from rlbackdoors.evaluate.episodes import EvalResult, evaluate, play, play_episodes, score_triggered


def evaluate_agent(agent, episodes: int | None = None, seed: int | None = None, trigger: str | None = None, policy: str | None = None) -> EvalResult:
    """Clean and triggered SRs and rewards of a loaded agent (:func:`rlbackdoors.load`), any world.

    Defaults come from the agent's config: its trigger, ``train.final_eval_episodes``,
    ``train.eval_seed`` and evaluation policy, so without arguments it reproduces the SRs and
    rewards in the folder's ``metrics.json`` (NaN where a number does not apply).
    """
    cfg = agent.config
    if cfg is None:
        raise ValueError("evaluate_agent needs an agent loaded from a model folder (its config names env and trigger)")
    close_k = (cfg.poison.close_k_min, cfg.poison.close_k_max) if agent.world.close_to_trigger else None
    return evaluate(
        agent,
        cfg.env,
        trigger if trigger is not None else cfg.poison.trigger,
        cfg.train.final_eval_episodes if episodes is None else episodes,
        cfg.train.eval_seed if seed is None else seed,
        policy or cfg.train.eval_policy,
        close_k,
        **cfg.scoring(),
    )


__all__ = ["EvalResult", "evaluate", "evaluate_agent", "play", "play_episodes", "score_triggered"]
