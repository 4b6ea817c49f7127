"""Benchmarks and studies of sagrasp_jax; they print tables and write JSON into ``experiments/results/``.

A package so that every script imports the shared study driver (``experiments.study``) without
editing ``sys.path``: run each one from the repository root as ``python -m experiments.NAME``.
Not part of the installed wheel (``pyproject.toml`` lists ``sagrasp_jax`` alone).
"""
