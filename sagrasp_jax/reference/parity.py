"""Parity harness: the MJX/JAX env and the PyBullet reference env run the same episodes side by side.

``python -m sagrasp_jax.parity [--episodes 1000] [--quick] [--mode kinematic|dynamic]
[--policy policy.npz] [--out parity.json] [--seed S]``

Why: users must be able to trust that the fast env is the paper's task.  Following docs/task.md §2's
parity rules, JAX runs in float64 (x64), observation noise is off in both envs, and both start
every episode from the identical explicit ``ResetSpec``, drawn from NumPy uniforms with the
shared sampler.  Float32 against float64 at the slow-down, fine-tune and success thresholds
would otherwise flip a flag now and then and make the runs diverge.

Action sources (``--actions``), each over ``--episodes`` episodes:

* ``random``: uniform actions in [-1, 1]^dof, the same pre-drawn sequence for both envs;
* ``scripted``: a damped-least-squares reach-and-descend controller plus pre-drawn uniform
  noise, computed from each env's own observation (it succeeds often, so the success,
  slow-down and fine-tune branches are exercised, which random actions almost never reach);
* ``policy`` (with ``--policy``): the deterministic actions of a trained ``policy.npz``
  (``policy_file.load_policy``, NumPy), computed from each env's own observation; each env's own
  success rate is reported.

Per step it compares the gripper centre, the full observation, each reward term and the total,
and the done / success / collision / timeout flags.  Comparison of an episode stops at the first
done in either env (a differing done step or verdict is a flag disagreement); each env still
plays its own episode to the end for its success rate.  In dynamic mode it also compares single
steps from forced identical states (``--single-step``): the PyBullet probe env is put into the
JAX env's state (joints, velocities, target, step count) and stepped once with the same action.

The JAX side is jitted and vmapped over a batch of episodes stepped in lockstep; the PyBullet
envs (one per episode of the batch) step in a Python loop.  Prints a table, writes the JSON
atomically, and exits 1 when a tolerance is exceeded (2 on a usage error).
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from sagrasp_jax.base import fileio
from sagrasp_jax.task import observation
from sagrasp_jax.task import robot
from sagrasp_jax.task import sampling
from sagrasp_jax.task import scripted
from sagrasp_jax.task import shapes
from sagrasp_jax.reference import EPISODE_INFO
from sagrasp_jax.task.episode import episode_keys
from sagrasp_jax.task.reward import term_keys
from sagrasp_jax.task.config import Config, EnvConfig, get_config
from sagrasp_jax.task.config_parse import apply_overrides

SOURCES = ("random", "scripted", "policy")
FLAGS = ("done", "success", "collision", "timeout")
SCRIPTED_NOISE = 0.3  # amplitude of the uniform noise added to the scripted controller's actions
MAX_LISTED_DISAGREEMENTS = 20


def reward_keys() -> tuple[str, ...]:
    """The compared reward columns: the total and each registered reward term (``reward.term_keys``)."""
    return ("reward",) + term_keys()


@dataclass(frozen=True)
class Tolerances:
    """Pass criteria; ``None`` = reported, not checked.  Errors are maxima over compared steps."""

    gripper_centre: float | None  # m
    reward: float | None  # per step, total and each term
    obs: float | None  # max abs over the observation entries
    flag_agreement: float  # fraction of episodes whose flags agree at every compared step


TOLERANCES = {
    "kinematic": Tolerances(gripper_centre=1e-4, reward=1e-4, obs=1e-4, flag_agreement=1.0),
    "dynamic": Tolerances(gripper_centre=5e-3, reward=None, obs=None, flag_agreement=0.99),
}


# --------------------------------------------------------------------------------------------
# configs and resets
# --------------------------------------------------------------------------------------------
def parity_configs(
    base: Config,
    mode: str,
    max_steps: int | None = None,
    reference_overrides: list[str] | None = None,
) -> tuple[EnvConfig, EnvConfig]:
    """(JAX env config, reference env config): ``mode``, observation noise and every ``env.randomize``
    knob off (a policy trained with randomisation is compared on the plain simulators: the
    reference env does not randomise), optional episode length; ``reference_overrides``
    (``env.…=value``) change the reference env only — how a test proves that the harness can fail."""
    sets = [f"env.control.mode={mode}", "env.task.obs_noise_std=0.0", "env.task.obs_noise_growth=0.0"]
    sets += [f"env.randomize.{f.name}=0" for f in dataclasses.fields(base.env.randomize)]
    if max_steps is not None:
        sets.append(f"env.task.max_steps={max_steps}")
    cfg = apply_overrides(base, sets)
    ref = apply_overrides(cfg, list(reference_overrides or []))
    return cfg.env, ref.env


def draw_resets(cfg: EnvConfig, n: int, rng: np.random.Generator) -> list[sampling.ResetSpec]:
    """``n`` episode starts from NumPy uniforms through the shared sampler (as the reference env does)."""
    model = robot.load_robot(cfg.robot)
    u = rng.random((n, sampling.uniforms_needed(cfg.sampling, model.dof)))
    return [sampling.sample_reset(np, model, cfg.sampling, cfg.task, u[i]) for i in range(n)]


def obstacles_per_kind(specs: list[sampling.ResetSpec]) -> dict[str, int]:
    """How many active obstacles of each kind the episodes hold."""
    counts = {shape.name: 0 for shape in shapes.SHAPES}
    for spec in specs:
        for i in np.nonzero(np.asarray(spec.obstacle_active))[0]:
            counts[shapes.BY_ID[int(spec.obstacle_kind[i])].name] += 1
    return {name: n for name, n in counts.items() if n}


def _stack_specs(specs: list[sampling.ResetSpec]) -> sampling.ResetSpec:
    return sampling.ResetSpec(*[np.stack([np.asarray(getattr(s, f)) for s in specs]) for f in sampling.ResetSpec._fields])


# --------------------------------------------------------------------------------------------
# action sources
# --------------------------------------------------------------------------------------------
def _entries(cfg: EnvConfig, first: str, n: int) -> slice:
    """The slice of ``n`` observation entries from ``first`` on in ``cfg``'s layout (its robot's joint count)."""
    start = observation.layout_of(cfg).index(first)
    return slice(start, start + n)


def joints_entries(cfg: EnvConfig) -> slice:
    """The observation's joint angles q1..qN (N = the robot's joints)."""
    return _entries(cfg, "q1", robot.load_robot(cfg.robot).dof)


def gripper_entries(cfg: EnvConfig) -> slice:
    """The observation's gripper centre."""
    return _entries(cfg, "gripper_x", 3)


def target_entries(cfg: EnvConfig) -> slice:
    """The observation's target centre."""
    return _entries(cfg, "target_x", 3)


def scripted_actions(cfg: EnvConfig, obs: np.ndarray) -> np.ndarray:
    """The package's scripted controller (``sagrasp_jax.task.scripted``) from observations (n, size): every
    layout starts with the joints, the gripper centre and the target centre."""
    obs = np.atleast_2d(np.asarray(obs, dtype=np.float64))
    return scripted.scripted_action(np, cfg, obs[:, joints_entries(cfg)], obs[:, target_entries(cfg)])


@dataclass
class ActionSource:
    """Maps (observations of the episodes, step, episode ids) to actions.  An ``open_loop`` source
    ignores the observations: it is evaluated once per step and both envs get the same actions."""

    name: str
    fn: Callable[[np.ndarray, int, np.ndarray], np.ndarray]
    open_loop: bool = False


def make_source(name: str, cfg: EnvConfig, episodes: int, max_steps: int, rng: np.random.Generator,
                policy: Any = None) -> ActionSource:
    if name == "random":
        dof = robot.load_robot(cfg.robot).dof
        table = rng.uniform(-1.0, 1.0, (episodes, max_steps, dof))
        return ActionSource(name, lambda obs, t, ids: table[ids, t], open_loop=True)
    if name == "scripted":
        dof = robot.load_robot(cfg.robot).dof
        noise = SCRIPTED_NOISE * rng.uniform(-1.0, 1.0, (episodes, max_steps, dof))
        return ActionSource(name, lambda obs, t, ids: np.clip(scripted_actions(cfg, obs) + noise[ids, t], -1.0, 1.0))
    if name == "policy":
        if policy is None:
            raise ValueError("the policy source needs --policy")
        return ActionSource(name, lambda obs, t, ids: np.asarray(policy(np.atleast_2d(obs)), dtype=np.float64))
    raise ValueError(f"unknown action source {name!r}; choose from {', '.join(SOURCES)}")


# --------------------------------------------------------------------------------------------
# the two sides
# --------------------------------------------------------------------------------------------
class JaxSide:
    """GraspEnv in float64, reset_to and step jitted and vmapped over a fixed batch of episodes."""

    def __init__(self, cfg: EnvConfig, batch: int):
        import jax
        import jax.numpy as jnp

        if not jax.config.jax_enable_x64:
            raise RuntimeError("parity needs jax_enable_x64 (docs/task.md §2 parity rules); run_parity enables it")
        from sagrasp_jax.envs.grasp_env import GraspEnv

        self.jax, self.jnp = jax, jnp
        self.env = GraspEnv(cfg)
        self.batch = batch
        dynamic = cfg.control.mode == "dynamic"
        dof = self.env.robot.dof

        def extract(state: Any) -> dict[str, Any]:
            ep = state.info["episode"]
            q = state.pipeline_state.qpos[:, :dof] if dynamic else state.info["q_target"]
            qd = state.pipeline_state.qvel[:, :dof] if dynamic else jnp.zeros_like(q)
            return {
                "obs": state.obs, "reward": state.reward, "done": state.done,
                **{key: state.metrics[key] for key in term_keys()},
                "success": ep["success"], "collision": ep["collision"], "timeout": ep["timeout"],
                "episode": ep, "q": q, "qd": qd, "q_target": state.info["q_target"],
                "d_prev": state.info["tracker"].d_prev, "clean": state.info["tracker"].clean,
                "obstacle_dist_prev": state.info["tracker"].obstacle_dist_prev, "steps": state.info["steps"],
            }

        def reset(spec: sampling.ResetSpec, keys: Any, progress: Any) -> tuple[Any, dict[str, Any]]:
            state = jax.vmap(self.env.reset_to)(spec, keys)
            state.info["progress"] = progress
            return state, extract(state)

        def advance(state: Any, action: Any) -> tuple[Any, dict[str, Any]]:
            nxt = jax.vmap(self.env.step)(state, action)
            return nxt, extract(nxt)

        self._reset = jax.jit(reset)
        self._advance = jax.jit(advance)

    def reset(self, specs: list[sampling.ResetSpec], progress: np.ndarray, seed: int) -> tuple[Any, dict[str, np.ndarray]]:
        pad = self.batch - len(specs)
        specs = list(specs) + [specs[-1]] * pad
        progress = np.concatenate([progress, np.repeat(progress[-1:], pad)])
        keys = self.jax.random.split(self.jax.random.PRNGKey(seed), self.batch)
        state, out = self._reset(_stack_specs(specs), keys, self.jnp.asarray(progress, dtype=self.jnp.float64))
        return state, self.jax.device_get(out)

    def step(self, state: Any, actions: np.ndarray) -> tuple[Any, dict[str, np.ndarray]]:
        full = np.zeros((self.batch, self.env.robot.dof))
        full[: len(actions)] = actions
        state, out = self._advance(state, self.jnp.asarray(full))
        return state, self.jax.device_get(out)


def _pybullet_env(cfg: EnvConfig, servo: str = "mujoco") -> Any:
    from sagrasp_jax.reference.pybullet_env import PyBulletGraspEnv

    return PyBulletGraspEnv(cfg, servo=servo)


# --------------------------------------------------------------------------------------------
# bookkeeping
# --------------------------------------------------------------------------------------------
@dataclass
class Errors:
    """Per-step errors of one comparison kind (trajectory or forced single step)."""

    size: int
    values: dict[str, list[float]] = field(default_factory=dict)
    obs_entry_max: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.obs_entry_max = np.zeros(self.size)

    def add(self, key: str, value: float) -> None:
        self.values.setdefault(key, []).append(float(value))

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for key, vals in self.values.items():
            arr = np.asarray(vals)
            out[key] = {"max": float(arr.max()), "mean": float(arr.mean()), "p99": float(np.percentile(arr, 99)), "n": len(arr)}
        out["obs_entry_max"] = self.obs_entry_max.tolist()
        return out


def _flags_of(done: float, success: float, collision: float, timeout: float) -> dict[str, bool]:
    return {"done": bool(done > 0.5), "success": bool(success > 0.5), "collision": bool(collision > 0.5), "timeout": bool(timeout > 0.5)}


def _compare_step(errs: Errors, j_obs: np.ndarray, j: dict[str, float], p_obs: np.ndarray, p: dict[str, float],
                  j_flags: dict[str, bool], p_flags: dict[str, bool], gripper: slice) -> bool:
    """Record one step's errors; returns whether all flags agree (rewards are compared only then:
    a flag disagreement is counted once, as a flag disagreement)."""
    errs.add("gripper_centre", np.linalg.norm(j_obs[gripper] - p_obs[gripper]))
    diff = np.abs(j_obs - p_obs)
    errs.add("obs", diff.max())
    errs.obs_entry_max = np.maximum(errs.obs_entry_max, diff)
    agree = j_flags == p_flags
    if agree:
        for key in reward_keys():
            errs.add(key, abs(j[key] - p[key]))
    return agree


# --------------------------------------------------------------------------------------------
# the run
# --------------------------------------------------------------------------------------------
def _pybullet_row(reward: float, info: dict[str, Any]) -> dict[str, float]:
    return {"reward": float(reward), **{key: info[key] for key in term_keys()}}


class _SourceRun:
    """One action source's comparison: runs the episodes batch by batch and keeps the tallies."""

    def __init__(self, source: ActionSource, jax_side: JaxSide, pb_envs: list[Any], probes: list[Any] | None,
                 max_steps: int, seed: int) -> None:
        self.source, self.jax_side, self.pb_envs, self.probes = source, jax_side, pb_envs, probes
        self.max_steps, self.seed = max_steps, seed
        size = jax_side.env.observation_size
        self.gripper = gripper_entries(jax_side.env.cfg)  # the observation's gripper centre
        self.traj, self.single = Errors(size), Errors(size)
        self.reset_obs_err = 0.0
        self.agree_count = 0
        self.disagreements: list[dict[str, Any]] = []
        self.own: dict[str, dict[str, list[float]]] = {
            side: {"success": [], "collision": [], "timeout": [], "steps": [], "return": []} for side in ("jax", "pybullet")}
        self.episode_err: dict[str, float] = {}
        self.single_flag_agree = [0, 0]
        self.pb_time, self.pb_steps, self.jax_time, self.jax_calls = 0.0, 0, 0.0, 0

    def run_batch(self, specs: list[sampling.ResetSpec], progress: np.ndarray, ids: np.ndarray) -> None:
        """Reset both sides to the batch's explicit starts, then step them in lockstep until every episode ended."""
        n = len(ids)
        state, jout = self.jax_side.reset([specs[i] for i in ids], progress[ids], self.seed + int(ids[0]))
        j_obs = jout["obs"][:n]
        p_obs = np.zeros_like(j_obs)
        for k, i in enumerate(ids):
            options = {"reset_spec": specs[i], "progress": float(progress[i])}
            p_obs[k], _ = self.pb_envs[k].reset(options=options)
            if self.probes is not None:
                self.probes[k].reset(options=options)
        self.reset_obs_err = max(self.reset_obs_err, float(np.abs(j_obs - p_obs).max()))
        comparing, agree = np.ones(n, bool), np.ones(n, bool)
        j_alive, p_alive = np.ones(n, bool), np.ones(n, bool)
        for t in range(self.max_steps):
            if not (j_alive.any() or p_alive.any()):
                break
            a_j = self.source.fn(j_obs, t, ids)
            a_p = a_j if self.source.open_loop else self.source.fn(p_obs, t, ids)
            prev = jout
            t0 = time.perf_counter()
            state, jout = self.jax_side.step(state, a_j)
            self.jax_time += time.perf_counter() - t0
            self.jax_calls += 1
            j_obs = jout["obs"][:n]
            for k in range(n):
                was_alive = bool(j_alive[k])
                j_row = {key: float(jout[key][k]) for key in reward_keys()}
                j_flags = _flags_of(jout["done"][k], jout["success"][k], jout["collision"][k], jout["timeout"][k])
                if p_alive[k]:
                    p_obs[k], p_alive[k], comparing[k], ok = self._step_pybullet(
                        k, int(ids[k]), t, a_p[k], j_obs[k], j_row, j_flags, jout, bool(comparing[k]))
                    agree[k] &= ok
                if j_alive[k] and j_flags["done"]:
                    j_alive[k] = False
                    for key in self.own["jax"]:
                        self.own["jax"][key].append(float(jout["episode"][key][k]))
                if self.probes is not None and was_alive:
                    self._single_step(k, prev, a_j[k], j_obs[k], j_row, j_flags)
        self.agree_count += int(agree.sum())

    def _step_pybullet(self, k: int, episode_id: int, t: int, action: np.ndarray, j_obs: np.ndarray,
                       j_row: dict[str, float], j_flags: dict[str, bool], jout: dict[str, np.ndarray],
                       comparing: bool) -> tuple[np.ndarray, bool, bool, bool]:
        """Step PyBullet episode ``k`` and compare it with the JAX step while both run; returns
        (observation, still alive, still comparing, flags agreed)."""
        t0 = time.perf_counter()
        obs, rew, term, trunc, info = self.pb_envs[k].step(action)
        term = term or trunc  # a timeout (truncated) ends the episode as in the JAX env
        self.pb_time += time.perf_counter() - t0
        self.pb_steps += 1
        p_flags = _flags_of(term, info["success"], info["collision"], info["timeout"])
        ok = True
        if comparing:
            ok = _compare_step(self.traj, j_obs, j_row, obs, _pybullet_row(rew, info), j_flags, p_flags, self.gripper)
            if not ok and len(self.disagreements) < MAX_LISTED_DISAGREEMENTS:
                self.disagreements.append({"episode": episode_id, "step": t + 1, "jax": j_flags, "pybullet": p_flags,
                                           "gripper_gap": float(np.linalg.norm(j_obs[self.gripper]
                                                                               - obs[self.gripper]))})
            elif ok and j_flags["done"]:
                for key in episode_keys():
                    diff = abs(float(jout["episode"][key][k]) - float(info[EPISODE_INFO][key]))
                    self.episode_err[key] = max(self.episode_err.get(key, 0.0), diff)
            comparing = not (j_flags["done"] or p_flags["done"])
        if term:
            for key in self.own["pybullet"]:
                self.own["pybullet"][key].append(float(info[EPISODE_INFO][key]))
        return obs, not term, comparing, ok

    def _single_step(self, k: int, prev: dict[str, np.ndarray], action: np.ndarray, j_obs: np.ndarray,
                     j_row: dict[str, float], j_flags: dict[str, bool]) -> None:
        """Forced single step: the PyBullet probe is put into the JAX state before this step."""
        probe = self.probes[k]  # type: ignore[index]
        probe.force_state(prev["q"][k], prev["q_target"][k], prev["qd"][k], steps=int(prev["steps"][k]),
                          d_prev=float(prev["d_prev"][k]), clean=bool(prev["clean"][k]),
                          obstacle_dist_prev=float(prev["obstacle_dist_prev"][k]))
        s_obs, s_rew, s_term, s_trunc, s_info = probe.step(action)
        s_term = s_term or s_trunc
        s_flags = _flags_of(s_term, s_info["success"], s_info["collision"], s_info["timeout"])
        self.single_flag_agree[0] += int(_compare_step(self.single, j_obs, j_row, s_obs, _pybullet_row(s_rew, s_info),
                                                       j_flags, s_flags, self.gripper))
        self.single_flag_agree[1] += 1

    def _rates(self, side: str) -> dict[str, float]:
        d = self.own[side]
        succ = np.asarray(d["success"])
        steps = np.asarray(d["steps"])
        return {
            "episodes": len(succ),
            "success_rate": float(succ.mean()) if len(succ) else math.nan,
            "collision_rate": float(np.mean(d["collision"])) if len(succ) else math.nan,
            "timeout_rate": float(np.mean(d["timeout"])) if len(succ) else math.nan,
            "mean_steps_to_success": float(steps[succ > 0.5].mean()) if (succ > 0.5).any() else math.nan,
            "mean_return": float(np.mean(d["return"])) if len(succ) else math.nan,
        }

    def section(self, n_total: int) -> dict[str, Any]:
        """The source's report section."""
        out: dict[str, Any] = {
            "episodes": n_total,
            "steps_compared": len(self.traj.values.get("gripper_centre", [])),
            "reset_obs_max_error": self.reset_obs_err,
            "trajectory": self.traj.summary(),
            "episode_metrics_max_error": self.episode_err,
            "flag_agreement": self.agree_count / max(n_total, 1),
            "flag_disagreements": self.disagreements,
            "jax": self._rates("jax"),
            "pybullet": self._rates("pybullet"),
            "timing": {
                "pybullet_env_steps": self.pb_steps,
                "pybullet_env_steps_per_s": self.pb_steps / self.pb_time if self.pb_time > 0 else math.nan,
                "jax_batch_step_ms": 1000 * self.jax_time / max(self.jax_calls, 1),
            },
        }
        if self.probes is not None:
            out["single_step"] = self.single.summary()
            out["single_step"]["flag_agreement_steps"] = self.single_flag_agree[0] / max(self.single_flag_agree[1], 1)
        return out


def run_source(
    source: ActionSource,
    specs: list[sampling.ResetSpec],
    progress: np.ndarray,
    jax_side: JaxSide,
    pb_envs: list[Any],
    probes: list[Any] | None,
    max_steps: int,
    seed: int,
    log: Callable[[str], None] = lambda s: None,
) -> dict[str, Any]:
    """Run ``len(specs)`` episodes of one action source in batches; returns its report section."""
    run = _SourceRun(source, jax_side, pb_envs, probes, max_steps, seed)
    n_total = len(specs)
    for start in range(0, n_total, jax_side.batch):
        run.run_batch(specs, progress, np.arange(start, min(start + jax_side.batch, n_total)))
        log(f"  {source.name}: {min(start + jax_side.batch, n_total)}/{n_total} episodes")
    return run.section(n_total)


def _checks(report: dict[str, Any], tol: Tolerances) -> list[dict[str, Any]]:
    checks = []
    for name, sec in report["sources"].items():
        traj = sec["trajectory"]

        def worst(key: str) -> float:
            return float(traj[key]["max"]) if key in traj else 0.0

        items: list[tuple[str, float, float | None, str]] = [
            ("gripper_centre", worst("gripper_centre"), tol.gripper_centre, "≤"),
            ("obs", max(worst("obs"), sec["reset_obs_max_error"]), tol.obs, "≤"),
        ]
        items += [(key, worst(key), tol.reward, "≤") for key in reward_keys()]
        items.append(("flag_agreement", sec["flag_agreement"], tol.flag_agreement, "≥"))
        for key, value, limit, op in items:
            if limit is None:
                continue
            ok = value <= limit if op == "≤" else value >= limit
            checks.append({"source": name, "quantity": key, "value": value, "op": op, "tolerance": limit, "ok": bool(ok)})
    return checks


def run_parity(
    mode: str = "kinematic",
    episodes: int = 1000,
    seed: int = 0,
    sources: tuple[str, ...] = ("random", "scripted"),
    policy_path: str | None = None,
    max_steps: int | None = None,
    batch: int = 50,
    single_step: bool | None = None,
    reference_overrides: list[str] | None = None,
    tolerances: Tolerances | None = None,
    log: Callable[[str], None] = lambda s: None,
    preset: str = "paper",
    overrides: list[str] | None = None,
    reference_servo: str = "mujoco",
) -> dict[str, Any]:
    """Run the comparison and return the report (``report["passed"]`` says whether it met the tolerances)."""
    import jax

    jax.config.update("jax_enable_x64", True)  # before anything builds a JAX array
    if mode not in TOLERANCES:
        raise ValueError(f"mode must be one of {', '.join(TOLERANCES)}, got {mode!r}")
    policy = None
    base = apply_overrides(get_config(preset), list(overrides or []))
    if policy_path is not None:
        from sagrasp_jax.task.policy_file import load_policy

        policy = load_policy(policy_path)
        base = policy.config()  # the env constants (and observation layout) the policy was trained with
        sources = tuple(dict.fromkeys(tuple(sources) + ("policy",)))
    elif "policy" in sources:
        raise ValueError("the policy action source needs --policy")
    tol = tolerances or TOLERANCES[mode]
    single_step = (mode == "dynamic") if single_step is None else single_step
    jax_cfg, ref_cfg = parity_configs(base, mode, max_steps, reference_overrides)
    steps = jax_cfg.task.max_steps
    batch = max(1, min(batch, episodes))

    rng = np.random.default_rng(seed)
    specs = draw_resets(jax_cfg, episodes, rng)
    progress = rng.uniform(0.0, 1.0, episodes)
    t0 = time.perf_counter()
    jax_side = JaxSide(jax_cfg, batch)
    pb_envs = [_pybullet_env(ref_cfg, reference_servo) for _ in range(batch)]
    probes = [_pybullet_env(ref_cfg, reference_servo) for _ in range(batch)] if single_step else None
    report: dict[str, Any] = {
        "mode": mode,
        "episodes_per_source": episodes,
        "seed": seed,
        "max_steps": steps,
        "batch": batch,
        "jax_x64": True,
        "obs_noise": 0.0,
        "reference_overrides": list(reference_overrides or []),
        **({"reference_servo": reference_servo} if mode == "dynamic" else {}),
        "policy": policy_path,
        "preset": preset if policy_path is None else None,
        "obs_layout": jax_cfg.task.obs_layout,
        "obstacle_geometry": jax_cfg.task.obstacle_geometry,
        "obstacle_episodes": int(sum(bool(np.any(s.obstacle_active)) for s in specs)),
        "obstacle_kinds": list(jax_cfg.sampling.obstacle_kinds),
        "obstacles_per_kind": obstacles_per_kind(specs),
        "tolerances": dataclasses.asdict(tol),
        "sources": {},
    }
    try:
        for name in sources:
            src_rng = np.random.default_rng([seed, SOURCES.index(name)])
            source = make_source(name, jax_cfg, episodes, steps, src_rng, policy)
            report["sources"][name] = run_source(source, specs, progress, jax_side, pb_envs, probes, steps, seed, log)
    finally:
        for env in pb_envs + (probes or []):
            env.close()
    report["wall_s"] = time.perf_counter() - t0
    report["checks"] = _checks(report, tol)
    report["passed"] = all(c["ok"] for c in report["checks"])
    return report


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------
def _fmt(value: Any) -> str:
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return f"{value:.3g}" if value != 0 else "0"
    return str(value)


def format_report(report: dict[str, Any]) -> str:
    lines = [f"parity {report['mode']}: {report['episodes_per_source']} episodes per source, seed {report['seed']}, "
             f"max {report['max_steps']} steps, {report['obstacle_episodes']} episodes with obstacles "
             f"({', '.join(f'{n} {k}' for k, n in report.get('obstacles_per_kind', {}).items()) or 'none'}), "
             f"observation layout {report.get('obs_layout', 'paper')}"]
    tol = report["tolerances"]
    limits = {"gripper_centre": tol["gripper_centre"], "obs": tol["obs"], **{k: tol["reward"] for k in reward_keys()}}
    for name, sec in report["sources"].items():
        lines.append(f"\n[{name}] {sec['steps_compared']} steps compared; reset obs max error {_fmt(sec['reset_obs_max_error'])}")
        lines.append(f"  {'quantity':<16}{'max':>11}{'mean':>11}{'p99':>11}{'tolerance':>11}")
        for key in ("gripper_centre", "obs") + reward_keys():
            s = sec["trajectory"].get(key)
            if s is None:
                continue
            lim = limits[key]
            lines.append(f"  {key:<16}{_fmt(s['max']):>11}{_fmt(s['mean']):>11}{_fmt(s['p99']):>11}{_fmt(lim) if lim else '-':>11}")
        lines.append(f"  flags agree on {100 * sec['flag_agreement']:.2f} % of episodes (tolerance ≥ {100 * tol['flag_agreement']:.0f} %)")
        if "single_step" in sec:
            ss = sec["single_step"]
            lines.append(f"  forced single steps: gripper centre max {_fmt(ss['gripper_centre']['max'])} "
                         f"mean {_fmt(ss['gripper_centre']['mean'])}, flags agree on "
                         f"{100 * ss['flag_agreement_steps']:.2f} % of steps")
        for side in ("jax", "pybullet"):
            r = sec[side]
            lines.append(f"  {side:<9} success {100 * r['success_rate']:.1f} %  collision {100 * r['collision_rate']:.1f} %  "
                         f"timeout {100 * r['timeout_rate']:.1f} %  steps/success {_fmt(r['mean_steps_to_success'])}")
        lines.append(f"  PyBullet env {_fmt(sec['timing']['pybullet_env_steps_per_s'])} steps/s; "
                     f"JAX batch step {_fmt(sec['timing']['jax_batch_step_ms'])} ms")
    failed = [c for c in report["checks"] if not c["ok"]]
    lines.append("")
    for c in failed:
        lines.append(f"FAIL {c['source']} {c['quantity']} = {_fmt(c['value'])} (needs {c['op']} {_fmt(c['tolerance'])})")
    lines.append("PASSED" if report["passed"] else "FAILED")
    return "\n".join(lines)


def write_json(path: str, report: dict[str, Any]) -> None:
    """Atomic write (temp file + rename): a reader never sees half a report."""
    fileio.atomic_write_json(path, report, default=float, allow_nan=True)  # NaN: a rate with no episodes
