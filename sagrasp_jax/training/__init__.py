"""The trainer: PPO (``agents/ppo/``: networks, losses, rollout, the jitted cycle), the lr and SA schedules,
the fixed-seed evaluation, checkpoints, run folders, seed groups over devices and processes.
Imports `base`, `task`, `envs`."""
