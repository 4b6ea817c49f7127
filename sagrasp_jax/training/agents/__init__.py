"""The learning algorithms' maths, one folder per agent as brax keeps them (``brax/training/agents/``)."""
