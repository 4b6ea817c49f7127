"""The task every backend shares: the robot (from the URDF), the scene, the obstacle shapes, the config, and
the maths (`xp` = numpy or jax.numpy) of collision, control, reward, observation, episode ends and sampling,
and the policy file's NumPy reader.  Imports only `base`; no jax (the robot PC installs this without it)."""
