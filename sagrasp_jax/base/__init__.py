"""Package infrastructure every layer may use: safe file I/O, the package's data files, the optional extras
and the message for a missing one, a run folder's file names.  Imports nothing else of the package; no jax."""
