"""``experiments/gpu_check.py``: its pure parts (the budget, the launch-relative clock, the policies' copy, a
stopped command's kill) with real numbers, and ``--quick`` end to end at CPU-smoke size: every section runs and
writes a JSON whose fields and numbers are sane, and the policies it copies load, so the check is ready when a
GPU is lent."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest

from experiments import gpu_check as g
from experiments.study import watch_trainer
from sagrasp_jax.task.policy_file import load_policy

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


# ---------------------------------------------------------------------- pure parts

def test_budget_keeps_the_later_sections_minimum_and_skips_with_the_reason() -> None:
    budget = g.Budget(100.0, 540.0, g.SECTIONS, quick=False)
    later_than_cold = sum(g.MIN_S[s][0] for s in ("warm", "envs16k", "physics", "paper"))
    assert later_than_cold == 195.0 and budget.section_end("cold") == 100.0 + 540.0 - 195.0
    assert budget.section_end("paper") == 640.0  # the last one has the deadline itself
    assert budget.skip_reason("cold", 110.0) is None
    reason = budget.skip_reason("paper", 630.0)  # 10 s left, it needs 30
    assert reason is not None and reason.startswith("skipped: 10 s of --budget-s 540") and "at least 30 s" in reason
    assert "skipped: 0 s" in (budget.skip_reason("physics", 700.0) or "")  # past its end: nothing negative said
    only = g.Budget(0.0, 100.0, ("cold", "paper"), quick=False)  # sections left out reserve nothing
    assert only.section_end("cold") == 70.0 and only.skip_reason("cold", 20.0) is None  # 50 s left: enough
    assert only.skip_reason("cold", 25.0) == ("skipped: 45 s of --budget-s 100 left for it, it needs at least 50 s "
                                              "(the sections after it keep 30 s)")
    quick = g.Budget(0.0, 900.0, g.SECTIONS, quick=True)
    assert {quick.section_end(s) for s in g.SECTIONS} == {900.0}


def test_parse_sections_keeps_the_checks_order_and_names_an_unknown_one() -> None:
    assert g.parse_sections("paper, cold") == ("cold", "paper")
    with pytest.raises(ValueError, match="unknown section.*nope.*valid: dynamic"):
        g.parse_sections("cold,nope")
    with pytest.raises(SystemExit) as exit_info:
        g.main(["--sections", "nope", "--out", os.devnull])
    assert exit_info.value.code == 2


def test_rows_are_timed_from_the_launch_at_which_they_were_first_seen() -> None:
    rows = [{"env_steps": 1000 * (i + 1), "time_s": 2.0 * (i + 1), "compile_s": 20.0, "steps_per_s": rate,
             **({"eval_success": ev} if ev is not None else {})}
            for i, (ev, rate) in enumerate([(0.5, 400.0), (None, 600.0), (0.985, 500.0), (0.991, 700.0)])]
    clock = g.RowClock()
    clock.stamp(rows[:1], 23.0)
    clock.stamp(rows[:1], 23.5)  # a poll with no new row stamps nothing
    clock.stamp(rows[:3], 26.0)
    clock.stamp(rows, 31.25)
    assert clock.seen_at == [23.0, 26.0, 26.0, 31.25]
    summary = g.run_summary(rows, clock.seen_at)
    assert summary["first_99"] == {"eval_success": 0.991, "env_steps": 4000, "train_s": 8.0, "from_launch_s": 31.25}
    assert summary["first_98"] == {"eval_success": 0.985, "env_steps": 3000, "train_s": 6.0, "from_launch_s": 26.0}
    assert summary["median_iteration_env_steps_per_s"] == 600.0 and summary["overall_env_steps_per_s"] == 500.0
    assert summary["last_eval_success"] == 0.991 and summary["env_steps"] == 4000 and summary["compile_s"] == 20.0
    assert g.first_at_level(rows, clock.seen_at, 0.995) is None
    assert g.run_summary([], [])["first_99"] is None


def test_quick_trains_the_suites_own_runs_so_the_compilation_cache_serves_it() -> None:
    from test_experiments import TINY_SETS
    from tiny_run import TINY_ARGS

    assert sorted(g.TINY) == sorted(TINY_ARGS[i + 1] for i, a in enumerate(TINY_ARGS) if a == "--set")
    assert TINY_ARGS[TINY_ARGS.index("--total-steps") + 1] == str(g.size("train_steps", True)) == "1024"
    assert TINY_ARGS[TINY_ARGS.index("--preset") + 1] == g.size("train_preset", True)
    assert list(g.PAPER_TINY) == TINY_SETS  # test_reproduce_paper_smoke's study: 8,192 steps, 2 seeds, 16 episodes
    assert (g.size("paper_steps", True), g.size("paper_seeds", True), g.size("paper_eval_episodes", True)) == (8192, 2, 16)


def test_copy_run_files_takes_the_small_files_and_no_checkpoint(tmp_path: pytest.TempPathFactory,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    run, dest = tmp_path / "run", tmp_path / "policies" / "cold"
    run.mkdir()
    for name, nbytes in [("policy.npz", 10), ("config.json", 10), ("metrics.jsonl", 300), ("checkpoint.ckpt", 10),
                         ("evaluation-8ep-robot.json", 10), ("evaluation.json", 10), ("evaluation.lock", 1),
                         ("train.log", 10)]:
        (run / name).write_bytes(b"x" * nbytes)
    monkeypatch.setattr(g, "MAX_COPY_BYTES", 100)
    copied = g.copy_run_files(str(run), str(dest))
    assert copied == {"copied": ["config.json", "evaluation-8ep-robot.json", "evaluation.json", "policy.npz"],
                      "left_out": ["metrics.jsonl (300 bytes)"]}
    assert sorted(os.listdir(dest)) == copied["copied"]
    assert g.copy_run_files(str(tmp_path / "missing"), str(tmp_path / "p2")) == {"copied": [], "left_out": []}


def test_collect_policies_finds_every_run_folder_whatever_its_sections_status(tmp_path: pytest.TempPathFactory) -> None:
    work, policies = tmp_path / "work", tmp_path / "policies"
    for folder in ("cold", "physics", "paper/runs/ppo/seed0", "paper/runs/sa-ppo/seed3", "cache-gpu", "unrelated"):
        (work / folder).mkdir(parents=True)
        (work / folder / "policy.npz").write_bytes(b"x")
    (work / "paper" / "runs" / "ppo" / "group.lock").write_bytes(b"")  # a file beside the seed folders: no run
    (work / "paper" / "results.md").write_text("| PPO |")
    assert g.run_folders(str(work)) == {"cold": str(work / "cold"), "physics": str(work / "physics"),
                                        "paper/ppo/seed0": str(work / "paper/runs/ppo/seed0"),
                                        "paper/sa-ppo/seed3": str(work / "paper/runs/sa-ppo/seed3")}
    copied = g.collect_policies(str(work), str(policies))
    assert set(copied) == {"cold", "physics", "paper/ppo/seed0", "paper/sa-ppo/seed3"}
    assert all(v == {"copied": ["policy.npz"], "left_out": []} for v in copied.values())
    assert (policies / "paper" / "results.md").read_text() == "| PPO |" and not (policies / "unrelated").exists()


def test_a_stopped_command_that_ignores_sigterm_is_killed_after_the_grace(tmp_path: pytest.TempPathFactory) -> None:
    cmd = [sys.executable, "-c", "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
           "print('up', flush=True); time.sleep(60)"]
    t = time.perf_counter()
    rows, stopped, code, wall = watch_trainer(cmd, str(tmp_path), str(tmp_path / "log"), str(tmp_path / "none.jsonl"),
                                              0.2, lambda rows, since: "the budget" if since > 1.0 else None, grace_s=1.0)
    assert stopped == "the budget" and code == -9 and rows == []
    assert 2.0 <= wall < 10.0 and time.perf_counter() - t < 10.0


def test_a_recorded_training_that_fails_raises_with_the_trainers_own_status(tmp_path: pytest.TempPathFactory) -> None:
    """The recorder's process ends 0 whatever ``train.main`` returned: the check reads the status from its record."""
    with pytest.raises(RuntimeError, match=r"--preset nope .*exited 2: .*unknown preset 'nope'"):
        g.recorded_training(str(tmp_path), "bad", ["--preset", "nope", "--seed", "0"], str(tmp_path / "cache"),
                            time.perf_counter() + 120.0)
    with open(tmp_path / "bad.record.json", encoding="utf-8") as f:
        assert json.load(f)["exit"] == 2


def test_the_compile_recorder_keeps_a_compile_the_stop_interrupted() -> None:
    """SIGTERM's ``Terminated`` raised inside a compile leaves its entry without an end (and one waiting for the serial
    lock without a start): the record still has every program, the interrupted one's compile seconds unknown and
    beside the compiles after its start, instead of a KeyError that lost the whole record (exit 1)."""
    from experiments.readme_line import CompileRecorder

    recorder = CompileRecorder(0.0)
    base = {"thread": "MainThread", "cache": "miss", "cache_lines": []}
    recorder.compiles = [
        {**base, "module": "jit_done", "start_s": 1.0, "own_start_s": 1.0, "own_end_s": 2.0, "own_cpu_s": 0.9,
         "end_s": 2.0, "kept": 0},
        {**base, "module": "jit_cut", "start_s": 3.0, "own_start_s": 3.0},  # Terminated during the compile
        {**base, "module": "jit_beside", "start_s": 3.5, "own_start_s": 3.5, "own_end_s": 4.0, "own_cpu_s": 0.4,
         "end_s": 4.0, "kept": 1},
        {**base, "module": "jit_waiting", "start_s": 3.6},  # Terminated while it waited for the serial lock
    ]
    rows = {r["module"]: r for r in recorder.programs()}
    assert list(rows) == ["jit_done", "jit_cut", "jit_beside", "jit_waiting"]
    assert rows["jit_done"]["own_compile_s"] == 1.0 and rows["jit_done"]["beside"] == []
    assert rows["jit_cut"]["own_compile_s"] is None and rows["jit_cut"]["own_compile_cpu_s"] is None
    assert rows["jit_cut"]["beside"] == ["jit_beside"] and rows["jit_beside"]["beside"] == ["jit_cut"]
    assert rows["jit_waiting"]["own_compile_s"] is None and rows["jit_waiting"]["beside"] == []


def test_the_compile_recorder_keeps_the_compilers_debug_lines_out_of_the_commands_log() -> None:
    """Recording turns jax's compiler logger to DEBUG; with a root handler up (mujoco-mjx's root-level debug message
    sets one) its lines flooded the section's log (78-90 in the physics log). Only WARNING and above reach it now,
    and the recorder still reads the debug lines. In a fresh process: installing patches jax for good."""
    code = """
import logging
from experiments.readme_line import CompileRecorder
seen = []
class Keep(logging.Handler):
    def emit(self, record):
        seen.append(record.levelname)
logging.getLogger().addHandler(Keep())
recorder = CompileRecorder(0.0).install()
read = []
recorder._line = lambda record: read.append(record.levelname)
log = logging.getLogger("jax._src.compiler")
log.debug("Persistent compilation cache hit for 'jit_x' with key 'k'")
log.warning("a warning")
print(seen, read)
"""
    done = subprocess.run([sys.executable, "-c", code], cwd=g.ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "['WARNING'] ['DEBUG', 'WARNING']"


def test_a_recorded_training_is_stopped_at_its_end(tmp_path: pytest.TempPathFactory) -> None:
    """SIGTERMed 3 s after launch (before its first iteration can end): the trainer's status 143, or killed
    before its handler was up, and the row says it was the budget."""
    row = g.recorded_training(str(tmp_path), "cold", g.training_args(True), None, time.perf_counter() + 3.0)
    assert row["stopped_by"].startswith("the budget (its section's end") and row["exit"] in (143, -15), row
    assert row["env_steps"] == 0 and row["first_99"] is None and row["process_wall_s"] < 3.0 + g.GRACE_S + 5.0
    assert (row["compile"] is None) == (row["exit"] == -15) and row["peak_device_memory_bytes"] is None


def test_the_budget_skips_a_section_saying_why(tmp_path: pytest.TempPathFactory) -> None:
    """``--budget-s 0.5`` is spent by the device probe: every section is a skipped row with its reason, and the
    JSON is complete."""
    out = str(tmp_path / "g.json")
    assert g.main(["--quick", "--sections", "warm,cold", "--budget-s", "0.5", "--out", out,
                   "--work", str(tmp_path / "work")]) == 0
    with open(out, encoding="utf-8") as f:
        result = json.load(f)
    assert result["complete"] is True and result["backend"] == "cpu" and result["wall_s"] > 0.5
    for name in ("cold", "warm"):
        row = result["sections"][name]
        assert row["status"] == "skipped" and row["reason"].startswith("skipped: 0 s of --budget-s 0 left for it")
    assert any(line.startswith("warm      skipped: 0 s") for line in result["table"])


# ---------------------------------------------------------------------- --quick end to end

def _training(row: dict, preset: str, num_envs: int) -> None:
    """A recorded training's fields: the run, its launch-relative times and its compile breakdown."""
    assert row["status"] == "ok", row
    assert row["preset"] == preset and row["num_envs"] == num_envs and row["env_steps"] == 1024
    assert row["stopped_by"] == "finished" and row["exit"] == 0 and row["cache"] == "shared"
    assert row["train_s"] > 0 and row["compile_s"] > 0 and row["median_iteration_env_steps_per_s"] > 0
    assert row["process_wall_s"] > row["compile_s"] + row["train_s"] and row["process_cpu_s"] > 0
    for level in ("first_99", "first_98"):  # a tiny run rarely gets there; when it does, after its compile
        assert row[level] is None or row[level]["from_launch_s"] > row["compile_s"]
    assert row["peak_device_memory_bytes"] is None  # CPUs report none
    c = row["compile"]
    programs = c["programs"]
    assert c["exit"] == 0 and c["totals"]["programs"] == len(programs) >= 4 and c["imports_s"] > 0
    assert all(p["compile_s"] >= 0 and (p["trace_s"] is None or p["trace_s"] >= 0) for p in programs)
    assert all(p["cache"] in ("hit", "miss", "off") for p in programs)
    assert any((p["called_at"] or "").startswith("training/trainer.py") for p in programs)
    assert max(p["hlo_instructions"] or 0 for p in programs) > 1000  # the training program itself
    assert row["cache_entries_after"] >= row["cache_entries_before"] and row["cache_entries_after"] > 0


def test_gpu_check_quick_writes_sane_json(tmp_path: pytest.TempPathFactory) -> None:
    out = str(tmp_path / "out" / "gpu_check.json")
    res = subprocess.run([sys.executable, "-m", "experiments.gpu_check", "--quick", "--out", out,
                          "--work", str(tmp_path / "work")], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    with open(out, encoding="utf-8") as f:
        result = json.load(f)
    assert result["quick"] is True and result["backend"] == "cpu" and 0 < result["wall_s"] <= result["budget_s"] == 900
    assert result["complete"] is True
    sections = result["sections"]
    assert set(sections) == set(g.SECTIONS)  # the JSON sorts its keys; the table keeps the order

    dyn = sections["dynamic"]
    assert dyn["status"] == "ok", dyn
    assert dyn["jax"]["env_steps_per_s"] > 0 and dyn["jax"]["mode"] == "dynamic" and dyn["jax"]["batch"] == 16
    if result["versions"]["warp"] == "not installed":
        assert dyn["warp"] == dyn["equal"] == "not installed"
    else:  # MuJoCo Warp present: its rate and the equality test, or their errors (Warp's CPU path needs a compiler)
        assert dyn["warp"]["status"] in ("ok", "error") and dyn["equal"]["status"] in ("ok", "error")
        if dyn["equal"]["status"] == "ok":
            assert dyn["equal"]["max_abs_joint_diff"] >= 0.0 and dyn["equal"]["atol"] == 1e-5

    for name, preset, envs in [("cold", "cpu-quick", 64), ("warm", "cpu-quick", 64), ("envs16k", "cpu-quick", 32),
                               ("physics", "cpu-physics", 64)]:
        _training(sections[name], preset, envs)
    warm = sorted(sections["warm"]["compile"]["programs"], key=lambda p: -(p["hlo_instructions"] or 0))
    assert [p["cache"] for p in warm[:3]] == ["hit"] * 3, warm[:3]  # cold filled the cache: its large programs load

    robot = sections["physics"]["evaluations"]["robot"]
    assert robot["status"] == "ok", robot
    assert robot["overall"]["episodes"] == 8 and 0 <= robot["overall"]["successes"] <= 8
    assert robot["overall"]["success_rate"] == pytest.approx(robot["overall"]["successes"] / 8)
    assert 0 <= robot["obstacle"]["episodes"] <= 8 and robot["wall_s"] > 0
    assert (robot["steps_per_success"] is None) == (robot["overall"]["successes"] == 0)

    paper = sections["paper"]
    assert paper["status"] == "ok" and paper["finished"] is True and paper["stopped_by"] == "finished", paper
    assert paper["env_steps_per_run"] == 8192 and paper["seeds"] == 2
    assert {a: {s: (r["env_steps"], r["policy"]) for s, r in seeds.items()} for a, seeds in paper["progress"].items()} \
        == {a: {"0": (8192, True), "1": (8192, True)} for a in ("ppo", "sa-ppo")}
    for algo in ("ppo", "sa-ppo"):
        pooled = paper["table"]["algos"][algo]
        lo, hi = pooled["success_ci95_wilson_pct"]
        assert pooled["episodes"] == 32 and 0.0 <= lo <= pooled["success_pct"] <= hi <= 100.0
    assert paper["table"]["paired_ppo_minus_sa_ppo"]["seeds"] == [0, 1]
    assert any(line.startswith("| SA-PPO |") for line in paper["table"]["results_md"])

    policies = result["policies_dir"]
    assert policies == str(tmp_path / "out" / "policies")
    folders = ["cold", "warm", "envs16k", "physics"] + [f"paper/{a}/seed{s}" for a in ("ppo", "sa-ppo") for s in (0, 1)]
    for folder in folders:  # what rehearse --policy FOLDER reads
        path = os.path.join(policies, folder)
        assert "policy.npz" in result["policies"][folder]["copied"] and not os.path.exists(
            os.path.join(path, "checkpoint.ckpt")), folder
        policy = load_policy(path)
        policy.check_grasp_inputs()
    assert os.path.isfile(os.path.join(policies, "physics", "evaluation-8ep-robot.json"))
    assert os.path.isfile(os.path.join(policies, "paper", "results.json"))
    assert os.path.isfile(os.path.join(policies, "paper", "sa-ppo", "seed1", "evaluation.json"))  # the study's record
    assert "cold      cpu-quick preset, 64 envs: finished, cache shared" in res.stdout
    assert "paper     2 seeds x 2 algorithms, 8,192 env steps per run: finished" in res.stdout
    assert "written to" in res.stdout
