"""The CPU XLA flag the package sets on import: the one the installed jaxlib knows, never one it rejects."""

from __future__ import annotations

import importlib.metadata
import json
import os
import subprocess
import sys

import pytest

from sagrasp_jax.base import xla_flags

LEGACY, OPTION = xla_flags.LEGACY_FLAG, xla_flags.BACKEND_OPTION_FLAG


@pytest.mark.parametrize("version, flag", [
    ("0.4.30", LEGACY), ("0.10.2", LEGACY), ("0.10.2.dev20260101", LEGACY),
    ("0.11.0", OPTION), ("0.11.2", OPTION), ("0.12.0.1", OPTION), ("1.0.0", OPTION), ("0.3.25", None),
])
def test_flag_follows_the_jaxlib_version(version, flag):
    assert xla_flags.flag_for(version) == flag


def test_user_flags_are_kept_and_a_user_choice_wins():
    assert xla_flags.choose_flags({}, "0.11.2", ()) == OPTION
    kept = xla_flags.choose_flags({"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}, "0.10.2", ())
    assert kept == f"--xla_force_host_platform_device_count=2 {LEGACY}"
    for own in ("--xla_cpu_use_fusion_emitters=true", "--xla_backend_extra_options=foo=1",
                "--xla_backend_extra_options=xla_cpu_disable_new_fusion_emitters=false"):
        assert xla_flags.choose_flags({"XLA_FLAGS": own}, "0.11.2", ()) is None, own
    assert xla_flags.choose_flags({}, None, ()) is None  # no jaxlib: the robot side


@pytest.mark.parametrize("choice, backend, version, options, noted", [
    ("legacy", "cpu", "0.10.2", {}, False),
    ("new", "cpu", "0.10.2", {"xla_cpu_use_fusion_emitters": True}, False),
    ("new", "cpu", None, {"xla_cpu_use_fusion_emitters": True}, False),
    ("new", "gpu", "0.10.2", {}, False),  # a GPU compiles with its own emitters: nothing to choose
    ("new", "cpu", "0.11.2", {}, True),  # the switch is a backend-options map entry there: not per program
    ("new", "cpu", "0.12.0.1", {}, True),
])
def test_emitter_options_per_program(choice, backend, version, options, noted):
    got, note = xla_flags.emitter_options(choice, backend, version)
    assert got == options
    assert (note is not None) == noted
    if noted:
        assert version in note and "cpu_fusion_emitters" in note


def test_emitter_options_refuse_an_unknown_choice():
    with pytest.raises(ValueError, match="'fast'.*legacy, new"):
        xla_flags.emitter_options("fast", "cpu", "0.10.2")


def test_the_per_program_option_reaches_this_jaxlibs_xla():
    """The option changes the compiled program on the installed jaxlib (a program of elementwise chains, as the
    env's are): were it ignored, "new" would quietly train with the process's emitter."""
    import jax
    import jax.numpy as jnp

    def chain(x):
        for i in range(8):
            x = jnp.sin(x) * jnp.cos(x * 1.0001 + i) + jnp.tanh(x)
        return x.sum()

    x = jnp.linspace(0.0, 1.0, 4096)
    options, _ = xla_flags.emitter_options("new", jax.default_backend(), xla_flags.installed_jaxlib_version())
    assert options, "the suite runs on a CPU with jaxlib < 0.11"
    legacy = jax.jit(chain).lower(x).compile()
    new = jax.jit(chain).lower(x).compile(compiler_options=options)
    assert legacy.as_text() != new.as_text()
    assert abs(float(legacy(x)) - float(new(x))) <= 1e-4 * abs(float(legacy(x)))


def test_only_where_jax_runs_on_the_cpu():
    assert xla_flags.choose_flags({}, "0.11.2", ("xla_cuda12",)) is None
    assert xla_flags.choose_flags({"JAX_PLATFORMS": "cuda"}, "0.11.2", ()) is None
    assert xla_flags.choose_flags({"JAX_PLATFORMS": "cuda,cpu"}, "0.11.2", ()) is None
    assert xla_flags.choose_flags({"JAX_PLATFORMS": "cpu"}, "0.11.2", ("xla_cuda12",)) == OPTION


def test_jaxlib_version_read_without_importing_it():
    assert xla_flags.installed_jaxlib_version() == importlib.metadata.version("jaxlib")


def _child(code: str, extra_env: dict[str, str]) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_PLATFORMS")}
    env.update(extra_env)
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)


def test_the_installed_xla_accepts_what_the_package_sets():
    """A fresh process: import the package, then jax, and compile and run a program on the CPU.  XLA aborts
    the process (``Unknown flag in XLA_FLAGS``) when the package sets a flag the installed jaxlib lacks."""
    code = ("import os, json, sagrasp_jax, jax, jax.numpy as jnp\n"
            "y = jax.jit(lambda x: jnp.sin(x) * 2.0 + x)(jnp.arange(4.0))\n"
            "print(json.dumps({'flags': os.environ.get('XLA_FLAGS', ''), 'backend': jax.default_backend(),"
            " 'devices': jax.device_count(), 'y': [float(v) for v in y]}))")
    done = _child(code, {"XLA_FLAGS": "--xla_force_host_platform_device_count=2", "JAX_PLATFORMS": "cpu"})
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    expected = xla_flags.flag_for(importlib.metadata.version("jaxlib"))
    assert expected is not None and expected in out["flags"].split()
    assert "--xla_force_host_platform_device_count=2" in out["flags"].split()
    assert out["backend"] == "cpu" and out["devices"] == 2
    assert out["y"][1] == pytest.approx(2 * 0.8414709848 + 1.0, rel=1e-6)
