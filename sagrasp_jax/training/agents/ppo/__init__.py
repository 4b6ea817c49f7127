"""PPO's algorithm, as brax's ``training/agents/ppo``: ``actor_critic`` (the networks, their optimizer and the
policy's action maths), ``rollout`` (acting in the batched env), ``losses`` (GAE and the clipped surrogate) and
``ppo`` (one iteration and the jitted cycle).  The trainer's host machinery (run folders, checkpoints, schedules,
seed groups, devices) stays in ``training/``."""
