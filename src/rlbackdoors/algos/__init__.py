"""Training algorithms: PPO (:mod:`.ppo`, incl. recurrent) and OPAC² (:mod:`.opac2`).

Nothing is imported here: :mod:`rlbackdoors.config` imports each algorithm's config section
and the algorithms import the config, so the package itself stays empty.
"""
