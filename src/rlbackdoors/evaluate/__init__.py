"""Honest evaluation: clean and triggered success rates and rewards."""

from rlbackdoors.evaluate.episodes import EvalResult, evaluate, play_episodes, score_triggered


def evaluate_agent(agent, episodes: int | None = None, seed: int | None = None, trigger: str | None = None, policy: str | None = None) -> dict:
    """Clean and triggered SRs and rewards of a loaded agent (:func:`rlbackdoors.load`), any world.

    Defaults come from the agent's config: its trigger, ``train.final_eval_episodes``,
    ``train.eval_seed`` and evaluation policy, so without arguments it reproduces the SRs and
    rewards in the folder's ``metrics.json`` (NaN where a number does not apply).
    """
    cfg = agent.config
    if cfg is None:
        raise ValueError("evaluate_agent needs an agent loaded from a model folder (its config names env and trigger)")
    trigger = trigger if trigger is not None else cfg.poison.trigger
    seed = cfg.train.eval_seed if seed is None else seed
    if agent.world.algorithm == "opac2":
        from rlbackdoors.evaluate.safety import evaluate_safety

        if policy not in (None, "greedy"):
            raise ValueError("OPAC² agents are evaluated with their deterministic action (policy 'greedy')")
        n = cfg.train.final_eval_episodes if episodes is None else episodes
        return evaluate_safety(lambda obs: agent.act(obs, deterministic=True)[0], cfg.env, trigger, n, seed).to_dict()
    close_k = (cfg.poison.close_k_min, cfg.poison.close_k_max) if agent.world.close_to_trigger else None
    n = cfg.train.final_eval_episodes if episodes is None else episodes
    return evaluate(agent.policy, cfg.env, trigger, n, seed, policy or cfg.train.eval_policy, close_k=close_k).to_dict()


__all__ = ["EvalResult", "evaluate", "evaluate_agent", "play_episodes", "score_triggered"]
