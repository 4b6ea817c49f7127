"""The study driver (``experiments.study``) and smoke tests of the studies and benchmarks built on it
(tiny budgets, real env), run as ``python -m experiments.NAME`` from the repository root.

The tiny trainer shapes equal ``tests/tiny_run.py``'s, so jax's persistent compilation cache
built by one serves the other.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from experiments import bench_vs_paper_stack as bench
from experiments import compare_schedules as compare
from experiments import obstacle_ablation as ab
from experiments import study
from sagrasp_jax.training import stats
from experiments import reproduce_paper as repro

from conftest import SUITE_PPO

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

TINY_SETS = ["ppo.network.policy_hidden=32,32,32,32", "ppo.learning_rate=3e-4", "sa.decay=0.98", "ppo.num_envs=64",
             "ppo.num_epochs=1", "ppo.num_minibatches=1", "env.task.max_steps=50", "eval.episodes=8", "eval.num_cycles=4"]


def _sets(items: list[str]) -> list[str]:
    return [arg for item in items for arg in ("--set", item)]


def _run(args: list[str], timeout: float = 300) -> subprocess.CompletedProcess[str]:
    """``python -m experiments.NAME ARGS`` from the repository root."""
    return subprocess.run([sys.executable, "-m", *args], cwd=REPO, capture_output=True, text=True, timeout=timeout)


# ---------------------------------------------------------------------- pure helpers

def test_mean_ci_matches_t_interval() -> None:
    """SciPy's t-interval at every seed count (the hand-written table stopped at 30 and used 1.96 above:
    a 4 % narrower interval at 31 seeds); t_{0.975,2} is the tables' 4.303."""
    from scipy import stats as sps

    ci = stats.mean_ci([1.0, 2.0, 3.0])
    half = 4.303 * 1.0 / np.sqrt(3)
    assert ci["mean"] == pytest.approx(2.0) and ci["n"] == 3
    assert ci["ci95"] == pytest.approx([2.0 - half, 2.0 + half], abs=1e-3)  # the table's 3 decimals
    rng = np.random.default_rng(0)
    for n in (2, 5, 30, 31, 40, 200):
        values = rng.normal(0.9, 0.05, n)
        expected = sps.t.interval(0.95, n - 1, loc=values.mean(), scale=sps.sem(values))
        assert stats.mean_ci(list(values))["ci95"] == pytest.approx(list(expected), rel=1e-12)
    assert stats.t975(31) == pytest.approx(2.0395, abs=1e-4) and stats.t975(31) / 1.959964 > 1.04
    assert stats.mean_ci([5.0])["ci95"] == [None, None]
    assert stats.mean_ci([None, float("nan")])["mean"] is None


def test_band_and_curve_matrix_align_seeds_on_env_steps() -> None:
    runs = [[{"env_steps": 10, "x": 1.0}, {"env_steps": 20, "x": 3.0}],
            [{"env_steps": 10, "x": 3.0}, {"env_steps": 20, "x": None}]]
    x, y = stats.curve_matrix(runs, "x")
    assert x.tolist() == [10, 20] and np.isnan(y[1, 1])
    mean, lo, hi = stats.band(y)
    assert mean.tolist() == [2.0, 3.0]
    assert lo[0] < 2.0 < hi[0] and lo[1] == hi[1] == 3.0  # one seed at step 20: no band
    assert [v.tolist() for v in stats.band(y, "minmax")] == [[2.0, 3.0], [1.0, 3.0], [3.0, 3.0]]
    assert stats.band_kind("auto", 2) == "minmax" and stats.band_kind("auto", 3) == "t95"


def test_summarise_algo_pools_episodes() -> None:
    def ev(rate: float, steps: float) -> dict:
        group = {"episodes": 100, "success_rate": rate, "mean_steps_per_success": steps,
                 "collision_rate": 0.1, "timeout_rate": 1 - rate - 0.1}
        return {"overall": group, "obstacle_present": dict(group, episodes=20),
                "obstacle_absent": dict(group, episodes=80)}

    s = repro.summarise_algo([ev(0.8, 30.0), ev(0.4, 60.0)], [0, 1])
    assert s["pooled"]["episodes"] == 200 and s["pooled"]["success_pct"] == pytest.approx(60.0)
    assert s["pooled"]["steps_per_success"] == pytest.approx((80 * 30 + 40 * 60) / 120)
    lo, hi = s["pooled"]["success_ci95_wilson_pct"]
    assert lo < 60.0 < hi
    assert s["across_seeds"]["success_pct"]["mean"] == pytest.approx(60.0)
    assert s["pooled"]["obstacle_present"]["episodes"] == 40
    assert s["pooled"]["obstacle_present"]["success_pct"] == pytest.approx(60.0)


def test_first_reach() -> None:
    pts = [(1.0, 100, 0.1), (2.0, 200, 0.6), (3.0, 300, 0.9)]
    out = stats.first_reach(pts, [0.5, 0.95])
    assert out["0.5"] == {"time_s": 2.0, "env_steps": 200}
    assert out["0.95"] == "not reached in budget"


def test_t_test_p_values() -> None:
    assert stats.t_test_p(2.776, 4) == pytest.approx(0.05, abs=2e-4)
    assert stats.t_test_p(12.706, 1) == pytest.approx(0.05, abs=2e-4)
    assert stats.t_test_p(2.045, 29) == pytest.approx(0.05, abs=2e-4)
    assert stats.t_test_p(1.0, 1) == pytest.approx(0.5, abs=1e-9)
    assert stats.t_test_p(0.0, 7) == pytest.approx(1.0) and stats.t_test_p(-3.0, 6) == stats.t_test_p(3.0, 6)
    assert stats.t_test_p(2.0395, 31) == pytest.approx(0.05, abs=2e-4)  # past the old table's 30


def test_binomial_rates_match_the_results_doc() -> None:
    """docs/results.md's 'why every seed is a draw': at a true 99.66 % over 1,000 episodes a seed shows
    ≥ 99.5 % with probability 0.87 (all five seeds 0.50; at 99.56 %: 0.72 and 0.19); a true 98.5 % of 187
    obstacle episodes shows ≥ 98 % (≤ 3 failures) with 0.69 (five seeds 0.16)."""
    from scipy import stats as sps

    one = stats.rate_at_least(0.9966, 1000, 0.995)
    assert one == pytest.approx(sps.binom.sf(994, 1000, 0.9966)) and round(one, 2) == 0.87 and round(one ** 5, 2) == 0.50
    one = stats.rate_at_least(0.9956, 1000, 0.995)
    assert (round(one, 2), round(one ** 5, 2)) == (0.72, 0.19)
    one = stats.rate_at_least(0.985, 187, 0.98)
    assert one == pytest.approx(sps.binom.cdf(3, 187, 0.015)) and (round(one, 2), round(one ** 5, 2)) == (0.69, 0.16)
    assert stats.rate_at_least(0.5, 10, 0.0) == 1.0 and stats.rate_at_least(0.5, 10, 1.0) == pytest.approx(0.5 ** 10)


def test_paired_comparison() -> None:
    from scipy import stats as sps

    a, b = [80.0, 85.0, 90.0, 70.0], [78.0, 86.0, 85.0, 66.0]
    out = stats.paired(a, b)
    d = np.array(a) - np.array(b)
    half = 3.182 * d.std(ddof=1) / 2.0
    assert out["n"] == 4 and out["mean_diff"] == pytest.approx(d.mean())
    assert out["ci95"] == pytest.approx([d.mean() - half, d.mean() + half], abs=1e-3)  # the table's 3.182
    assert out["ci95"] == pytest.approx(list(sps.t.interval(0.95, 3, loc=d.mean(), scale=sps.sem(d))), rel=1e-12)
    assert out["t"] == pytest.approx(d.mean() / (d.std(ddof=1) / 2.0))
    assert out["p"] == pytest.approx(sps.ttest_1samp(d, 0.0).pvalue, rel=1e-12)
    assert out["p"] == pytest.approx(stats.t_test_p(out["t"], 3), rel=1e-12)
    assert (out["wins"], out["ties"], out["losses"]) == (3, 0, 1)
    assert 0.1 < out["p"] < 0.3
    assert stats.paired([100.0, 120.0], [110.0, 125.0], larger_is_better=False)["wins"] == 2  # fewer steps wins
    missing = stats.paired([1.0, None, 3.0], [0.0, 2.0, None])
    assert missing["n"] == 1 and missing["mean_diff"] == 1.0 and missing["p"] is None
    assert stats.paired([2.0, 3.0], [1.0, 2.0])["p"] == 0.0  # the same difference on every seed


def test_training_time_adds_up_sessions() -> None:
    rows = [{"time_s": 1.0}, {"time_s": 2.0}, {"time_s": 0.5}, {}, {"time_s": 1.5}]
    assert compare.training_time(rows) == [1.0, 2.0, 2.5, 2.5, 3.5]


def test_variant_tables_are_valid_configs() -> None:
    from sagrasp_jax import train

    assert list(compare.SCHEDULE_VARIANTS) == ["constant", "sa", "kl-adaptive", "cosine", "linear"]
    assert compare.ABLATION_VARIANTS["sa-no-plateau-decay"] == ("lr.schedule=sa", "sa.plateau_decay=false")
    for table in (compare.VARIANTS, ab.VARIANTS, repro.VARIANTS):
        for sets in table.values():
            train.build_config("cpu-quick", overrides=list(sets))
    # the paper's algorithms as variants give the configs `train --algo` gives
    for algo, sets in repro.VARIANTS.items():
        assert train.build_config("cpu-quick", None, 3, 8192, list(sets)) == train.build_config("cpu-quick", algo, 3, 8192)


def test_seeds_and_variant_choice() -> None:
    assert study.parse_seeds("3") == (0, 1, 2) and study.parse_seeds("2-4") == (2, 3, 4)
    assert study.parse_seeds("1,5") == (1, 5)
    for bad in ("0", "x", "1,1", "3-1"):
        with pytest.raises(study.StudyError, match="--seeds"):
            study.parse_seeds(bad)
    table = {"a": ("x=1",), "b": ()}
    assert study.pick_variants(table, None, ["b"]) == {"b": ()}
    assert study.pick_variants(table, " a ,b", []) == {"a": ("x=1",), "b": ()}
    with pytest.raises(study.StudyError, match="unknown variant"):
        study.pick_variants(table, "a,c", [])
    spec = study.Study("cpu-quick", 8192, (0, 1), "runs")
    assert spec.folder("+layout", 1) == os.path.join("runs", "+layout", "seed1")  # the layout of train --seeds
    record = {"conditions": {"robot": {"overall": {"episodes": 10, "success_rate": 0.7}}}}
    assert study.condition_rates(record) == {"success_condition_robot": 70.0} and study.condition_rates({}) == {}
    from sagrasp_jax.task.config import ConfigError

    with pytest.raises(ConfigError, match="unknown evaluation condition"):
        study.Evaluation(10, condition="moon")


def test_compare_with_reference_pairs_seeds() -> None:
    per_seed = {"ref": [{"seed": 0, "x": 1.0}, {"seed": 1, "x": 2.0}, {"seed": 2, "x": 3.0}],
                "v": [{"seed": 0, "x": 2.0}, {"seed": 2, "x": 3.5}]}
    out = stats.compare_with_reference(per_seed, "ref", [("x", True)])
    assert set(out) == {"v"} and out["v"]["seeds"] == [0, 2]
    assert out["v"]["x"]["mean_diff"] == pytest.approx(0.75) and out["v"]["x"]["wins"] == 2
    assert stats.compare_with_reference(per_seed, "missing", [("x", True)]) == {}


# ---------------------------------------------------------------------- CLI smoke tests

def test_ensure_trained_rule_for_every_folder_state(tmp_path: pytest.TempPathFactory,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """The folder rule of every study: refuse another config before deleting anything, skip finished
    runs, continue unfinished ones only with --resume (from the checkpoint, or afresh without one)."""
    from sagrasp_jax import train
    from sagrasp_jax.training import run_dir
    from sagrasp_jax.task.config import config_to_dict

    calls: list[tuple[str, bool]] = []
    def fake_run(cfg: object, out: str, resume: bool, progress: bool, stop_after_cycles: int | None) -> None:
        assert stop_after_cycles is None  # outside a screen a run trains to its end
        calls.append((out, resume))

    monkeypatch.setattr(study.train, "run", fake_run)
    cfg = train.build_config("cpu-quick", None, 0, 8192, [])
    other = train.build_config("cpu-quick", None, 1, 8192, [])

    def folder(name: str, config: object | None, *files: str) -> str:
        out = str(tmp_path / name)
        os.makedirs(out)
        if config is not None:
            with open(os.path.join(out, run_dir.CONFIG_FILE), "w", encoding="utf-8") as f:
                json.dump(config_to_dict(config), f)
        for extra in files:
            open(os.path.join(out, extra), "w").close()
        return out

    foreign_stale = folder("foreign", other, "lock")  # another seed's run, killed before its checkpoint
    with pytest.raises(study.StudyError, match="another config"):
        study.ensure_trained(foreign_stale, cfg, "t", False, resume=True)
    assert sorted(os.listdir(foreign_stale)) == sorted([run_dir.CONFIG_FILE, "lock"]) and calls == []

    assert study.ensure_trained(folder("done", cfg, run_dir.POLICY_FILE), cfg, "t", False, False) is None and calls == []
    partial = folder("partial", cfg, run_dir.CHECKPOINT_FILE)
    with pytest.raises(study.StudyError, match="--resume"):
        study.ensure_trained(partial, cfg, "t", False, resume=False)
    assert calls == []
    assert study.ensure_trained(partial, cfg, "t", False, resume=True) is not None and calls[-1] == (partial, True)
    stale = folder("stale", cfg, "metrics.jsonl")
    study.ensure_trained(stale, cfg, "t", False, resume=True)
    assert calls[-1] == (stale, False) and not os.path.exists(stale)  # removed, then trained afresh (fake run)
    bare = folder("bare", None, "lock")  # killed before its config was written
    study.ensure_trained(bare, cfg, "t", False, resume=True)
    assert calls[-1] == (bare, False) and len(calls) == 3


def test_run_study_trains_evaluates_skips_and_refuses_before_training(tmp_path: pytest.TempPathFactory,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """variants × seeds into <runs>/<variant>/seed<S>/, one record each; a second call skips them all;
    an unfinished folder anywhere stops the study (without --resume) before anything trains."""
    from sagrasp_jax import train
    from sagrasp_jax.training import run_dir
    from sagrasp_jax.task.config import config_to_dict

    trained: list[str] = []
    programs: list[list[int] | None] = []  # the seeds of each training call (None: a single run)

    def fake_run(cfg: object, out: str, resume: bool = False, progress: bool = True,
                 seeds: list[int] | None = None, stop_after_cycles: int | None = None) -> None:
        assert stop_after_cycles is None  # outside a screen a run trains to its end
        programs.append(seeds)
        for folder, c in ([(out, cfg)] if seeds is None else
                          [(train.seed_dir(out, s), train.seed_config(cfg, s)) for s in seeds]):
            os.makedirs(folder, exist_ok=True)
            with open(os.path.join(folder, run_dir.CONFIG_FILE), "w", encoding="utf-8") as f:
                json.dump(config_to_dict(c), f)
            open(os.path.join(folder, run_dir.POLICY_FILE), "w").close()
            trained.append(folder)

    monkeypatch.setattr(study.train, "run", fake_run)
    spec = study.Study("cpu-quick", 8192, (0, 2), str(tmp_path / "runs"), progress=False)
    table = {"a": ("ppo.num_envs=64",), "b": ("ppo.num_envs=128",)}
    measure = lambda folder, variant, seed: {"score": 10.0 * seed + len(variant)}  # noqa: E731
    records = study.run_study(spec, table, measure, {"episodes": 4}, "rec.json")
    assert [r["seed"] for r in records["a"]] == [0, 2] and records["b"][1]["score"] == 21.0
    assert records["a"][0]["overrides"] == ["ppo.num_envs=64"] and records["a"][0]["episodes"] == 4
    assert sorted(os.path.relpath(t, spec.runs_dir) for t in trained) == [
        os.path.join(v, f"seed{s}") for v in "ab" for s in (0, 2)]
    assert programs == [[0, 2], [0, 2]]  # each variant's new seeds: one seed group, one program
    again = study.run_study(spec, table, measure, {"episodes": 4}, "rec.json")
    assert again == records and len(trained) == 4
    one_by_one = dataclasses.replace(spec, runs_dir=str(tmp_path / "single"), group=False)
    study.run_study(one_by_one, {"a": table["a"]}, measure, {"episodes": 4}, "rec.json")
    assert programs[2:] == [None, None] and len(trained) == 6
    with pytest.raises(study.StudyError, match="another config"):  # the same folders under another variant's config
        study.run_study(spec, {"a": table["b"]}, measure, {"episodes": 4}, "rec.json")
    unfinished = spec.folder("c", 2)
    os.makedirs(unfinished)
    with open(os.path.join(unfinished, run_dir.CONFIG_FILE), "w", encoding="utf-8") as f:
        json.dump(config_to_dict(spec.config((), 2)), f)
    open(os.path.join(unfinished, run_dir.CHECKPOINT_FILE), "w").close()
    with pytest.raises(study.StudyError, match="--resume"):
        study.run_study(spec, {"new": (), "c": ()}, measure, {"episodes": 4}, "rec.json")
    assert len(trained) == 6 and not os.path.exists(spec.folder("new", 0))  # nothing trained


def test_reproduce_paper_smoke(tmp_path: pytest.TempPathFactory) -> None:
    pytest.importorskip("matplotlib")
    out, runs = str(tmp_path / "out"), str(tmp_path / "runs")
    args = ["experiments.reproduce_paper", "--preset", "cpu-quick", "--total-steps", "8192", "--seeds", "2",
            "--eval-episodes", "16", "--out-dir", out, "--runs-dir", runs, "--no-progress", *_sets(TINY_SETS)]
    res = _run(args)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    for name in ["results.json", "results.md", "sa_schedule.png", "fig15_summary.png"] + [c[0] for c in repro.CURVES]:
        assert os.path.getsize(os.path.join(out, name)) > 0, name
    for algo in repro.VARIANTS:
        for seed in (0, 1):
            run = os.path.join(runs, algo, f"seed{seed}")
            for name in ("config.json", "metrics.jsonl", "checkpoint.ckpt", "policy.npz", "evaluation.json"):
                assert os.path.isfile(os.path.join(run, name)), (run, name)
    with open(os.path.join(out, "results.json"), encoding="utf-8") as f:
        results = json.load(f)
    assert results["meta"]["seeds"] == [0, 1] and results["meta"]["total_steps"] == 8192
    for algo in repro.VARIANTS:
        pooled = results["algos"][algo]["pooled"]
        assert pooled["episodes"] == 32 and 0.0 <= pooled["success_pct"] <= 100.0
        lo, hi = pooled["success_ci95_wilson_pct"]
        assert 0.0 <= lo <= pooled["success_pct"] <= hi <= 100.0
        assert results["paper"][algo]["success_pct"] in (92.0, 98.0)
    paired = results["paired_ppo_minus_sa_ppo"]  # seed by seed, PPO minus SA-PPO
    assert paired["seeds"] == [0, 1] and paired["success_pct"]["n"] == 2
    with open(os.path.join(out, "results.md"), encoding="utf-8") as f:
        md = f.read()
    rows = [line for line in md.splitlines() if line.startswith("| PPO |") or line.startswith("| SA-PPO |")]
    assert len(rows) == 2 + 2 + 6  # main table, obstacle split, per-seed table (2 seeds + mean per algo)
    assert all(len(r.strip("|").split("|")) in (5, 6, 7) for r in rows)

    # Re-running skips the finished runs; another config for the same folders is refused.
    again = _run(args)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stdout.count("done already, skipped") == 4
    clash = _run(args[:-2] + ["--set", "eval.num_cycles=2"])
    assert clash.returncode == 2 and "another config" in clash.stderr


@pytest.mark.bench
def test_bench_train_run_section_smoke(tmp_path: pytest.TempPathFactory) -> None:
    """The README-command section: a cold-cache run watched to its end, then the warm-cache restart."""
    out = str(tmp_path / "bench.json")
    res = _run(["experiments.bench_train", "--sections", "run", "--seeds", "0", "--budget-s", "240", "--out", out,
                *_sets(TINY_SETS + ["train.total_steps=16384"])], timeout=400)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    with open(out, encoding="utf-8") as f:
        run = json.load(f)["run"]
    seed0 = run["runs"]["seed0"]
    assert seed0["stopped_by"] == "finished" and seed0["env_steps"] == 16384 and seed0["cycles"] == 4
    assert seed0["reset_replays"] == 0 and seed0["startup_s"] >= seed0["compile_s"] > 0
    assert 100 < seed0["peak_rss_mb"] < 8000 and seed0["median_iteration_env_steps_per_s"] > 0
    assert set(seed0["time_to_eval_success"]) == {"0.9", "0.95", "0.98", "0.99"}
    assert 0 < run["warm"]["compile_s"] and run["warm"]["startup_s"] > 0


def test_bench_train_group_reads_the_last_evaluation_of_a_run_folder(tmp_path: pytest.TempPathFactory) -> None:
    """The group section compares groups and single runs by their last per-cycle evaluation, read through
    run_dir (its import once pointed at names train no longer re-exports)."""
    from experiments import bench_train

    rows = [{"iteration": 1, "eval_success": 0.25}, {"iteration": 2}, {"iteration": 3, "eval_success": 0.75},
            {"iteration": 4, "loss": 0.1}]
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert bench_train.last_eval_success(str(tmp_path)) == 0.75
    (tmp_path / "metrics.jsonl").write_text(json.dumps({"iteration": 1}) + "\n")
    assert bench_train.last_eval_success(str(tmp_path)) is None


@pytest.mark.bench
def test_bench_train_epochs_smoke(tmp_path: pytest.TempPathFactory) -> None:
    """Fewer passes late: every variant timed, the late counts cheaper than eight passes per iteration and
    their projected README training shorter; a config value out of range exits 2."""
    out = str(tmp_path / "epochs.json")
    sets = [s for s in TINY_SETS if not s.startswith("ppo.num_epochs")] + ["ppo.num_epochs=8", "train.total_steps=16384"]
    res = _run(["experiments.bench_train", "epochs", "--reps", "2", "--out", out, *_sets(sets)])
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    with open(out, encoding="utf-8") as f:
        rows = {r["variant"]: r for r in json.load(f)["rows"]}
    assert set(rows) == {"8 passes throughout", "late_epochs=4 (from the start)", "late_epochs=2 (from the start)",
                         "num_epochs=4 (fixed scan)"}
    assert rows["late_epochs=2 (from the start)"]["ms_per_iteration"] < rows["8 passes throughout"]["ms_per_iteration"]
    assert rows["8 passes throughout"]["projected_readme_training_s"] is None
    assert 0 < rows["late_epochs=4 (from the start)"]["projected_readme_training_s"]
    bad = _run(["experiments.bench_train", "epochs", "--set", "ppo.late_from=1.5"])
    assert bad.returncode == 2 and "ppo.late_from" in bad.stderr and "Traceback" not in bad.stderr


@pytest.mark.bench
def test_bench_vs_paper_stack_smoke_without_sb3(tmp_path: pytest.TempPathFactory) -> None:
    out = str(tmp_path / "bench.json")
    args = ["experiments.bench_vs_paper_stack", "--seconds", "2", "--window", "16", "--success", "0.5",
            "--out", out, *_sets(TINY_SETS + ["train.total_steps=200000"])]
    res = _run(args)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    with open(out, encoding="utf-8") as f:
        result = json.load(f)
    assert result["sb3"]["status"] == "skipped" and "--sb3-python" in result["sb3"]["reason"]
    ours = result["ours"]
    assert ours["status"] == "ok" and ours["env_steps"] > 0 and ours["env_steps_per_s"] > 0
    assert ours["train_s"] >= 2.0 and ours["stopped_by_budget"]
    assert set(ours["time_to_success"]) == {"0.5"}
    assert result["ratio_ours_over_sb3_env_steps_per_s"] is None
    assert "skipped" in res.stdout


@pytest.mark.bench
def test_bench_vs_paper_stack_raw_dynamic_smoke(tmp_path: pytest.TempPathFactory) -> None:
    """``raw``: the bare PyBullet chain's dynamic stepping timed before and after ours, our dynamic env bare and
    through auto-reset on 1 and every device, the ratio of the best to the paper side; bad sizes exit 2."""
    pytest.importorskip("pybullet")
    out = str(tmp_path / "raw.json")
    res = _run(["experiments.bench_vs_paper_stack", "raw", "--batch", "4", "--scan-steps", "3", "--pybullet-steps",
                "20", "--out", out])
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    with open(out, encoding="utf-8") as f:
        result = json.load(f)
    paper = result["paper_raw_dynamic"]
    assert paper["env_steps_per_s_before"] > 0 and paper["env_steps_per_s_after"] > 0
    assert "12 x 1/240 s" in paper["what"]
    assert {(r["auto_reset"], r["devices"]) for r in result["ours"]} >= {(False, 1), (True, 1)}
    assert all(r["mode"] == "dynamic" and r["batch"] == 4 for r in result["ours"])
    best = max(r["env_steps_per_s"] for r in result["ours"] if r["auto_reset"])
    assert result["ratio_auto_reset"] == pytest.approx(best / paper["env_steps_per_s"])
    assert _run(["experiments.bench_vs_paper_stack", "raw", "--batch", "0"]).returncode == 2


def test_bench_sb3_missing_interpreter_is_skipped(tmp_path: pytest.TempPathFactory) -> None:
    res = bench.bench_sb3(str(tmp_path / "no-python"), 1.0, 16, [0.5], 16, str(tmp_path), 10.0)
    assert res["status"] == "skipped" and "does not exist" in res["reason"]
    if importlib.util.find_spec("stable_baselines3") is None:  # the test venv has no SB3: reported, not crashed
        res = bench.bench_sb3(sys.executable, 1.0, 16, [0.5], 16, str(tmp_path), 10.0)
        assert res["status"] == "skipped" and "cannot import" in res["reason"]


def test_compare_schedules_smoke(tmp_path: pytest.TempPathFactory) -> None:
    out, runs = str(tmp_path / "results" / "cmp.json"), str(tmp_path / "runs")  # results/ does not exist yet
    args = ["experiments.compare_schedules", "--preset", "cpu-quick", "--total-steps", "8192", "--seeds", "1",
            "--variants", "constant,sa", "--eval-episodes", "16", "--blocking-episodes", "8", "--out", out,
            "--runs-dir", runs, "--no-progress", *_sets(TINY_SETS)]
    res = _run(args)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    with open(out, encoding="utf-8") as f:
        result = json.load(f)
    assert set(result["summary"]) == {"constant", "sa"} and result["seeds"] == [0]
    for name in ("constant", "sa"):
        rec = result["runs"][name][0]
        assert rec["mix"]["episodes"] == 16 and rec["blocking_scenes"]["episodes"] == 8
        assert set(rec["reach"]) == {"0.9", "0.95", "0.98", "0.99"} and rec["cycles"] == 4
        s = result["summary"][name]
        assert 0.0 <= s["success_overall"]["mean"] <= 100.0 and s["success_overall"]["n"] == 1
    assert result["runs"]["constant"][0]["final_lr"] == 3e-4
    assert set(result["paired_vs_reference"]) == {"constant"}
    assert result["paired_vs_reference"]["constant"]["success_overall"]["n"] == 1
    assert "| constant |" in res.stdout and "Paired with `sa`" in res.stdout
    if importlib.util.find_spec("matplotlib") is not None:
        assert os.path.getsize(out[:-5] + "_curves.png") > 0 and os.path.getsize(out[:-5] + "_lr.png") > 0
        for name in ["fig15_summary.png", "sa_schedule.png"] + [c[0] for c in repro.CURVES]:  # Figures 11-15
            assert os.path.getsize(os.path.join(out[:-5] + "_figures", name)) > 0, name
    again = _run(args)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stdout.count("done already, skipped") == 2


def test_sooner_levers_each_change_what_they_name_and_nothing_else(capsys: pytest.CaptureFixture) -> None:
    """Every lever of the time-to-quality table is a valid config that differs from the baseline in exactly
    the keys it names (a lever that a preset change made a no-op would be measured as noise); the baseline is
    still the config its recorded runs were trained with, and today's preset is the combination that won;
    bad options exit 2."""
    from experiments import sooner, study
    from sagrasp_jax.training import evaluation
    from sagrasp_jax.task.config import config_to_dict

    spec = study.Study("cpu-quick", 3_000_000, (0,), "unused")
    def flat(cfg: object, prefix: str = "") -> dict:
        out: dict = {}
        for k, v in (config_to_dict(cfg) if prefix == "" else cfg).items():
            out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {prefix + k: v})
        return out

    def changes_only_what_it_names(over: dict, levers: dict[str, tuple[str, ...]], prefix: str) -> None:
        for name, sets in levers.items():
            changed = {k for k, v in flat(spec.config(sooner.LEVERS[prefix + name], 0)).items() if over[k] != v}
            assert changed == {s.split("=")[0] for s in sets}, prefix + name

    base = flat(spec.config(sooner.LEVERS[sooner.REFERENCE], 0))
    assert sooner.REFERENCE in sooner.DEFAULT and set(sooner.DEFAULT) <= set(sooner.LEVERS)
    changes_only_what_it_names(base, sooner._LEVERS, "")
    # the recorded baseline runs (sooner_levers3_3M.json, seed 0) were trained with exactly this config
    assert evaluation.config_identity(spec.config(sooner.LEVERS["baseline"], 0)) == "0d6b7c82eeef9d39"
    assert SUITE_PPO == list(sooner.BEFORE)  # the suite's short runs keep the shape the levers are measured over
    round_1 = flat(spec.config(sooner.ROUND_1, 0))  # BEFORE + the first round's winning lever
    changes_only_what_it_names(round_1, sooner._OVER_ADOPTED, "adopted+")  # the second round's levers
    # the first round's recorded runs (sooner_combo_10M.json, seed 0) keep their identity: a key added since
    # (obs_obstacle_shape) left it unchanged
    assert evaluation.config_identity(spec.config(sooner.ROUND_1, 0)) == "f2dcda76602f32b5"
    # the third round is measured over the second round's winner, pinned, and its winner is today's preset
    round_2 = flat(spec.config(sooner.ROUND_2, 0))
    assert round_2 == flat(spec.config(sooner.LEVERS["adopted+lr-6e-4+decay-0.96"], 0))
    # ... but for the CPU fusion emitters: today's preset compiles with the new ones (the same maths, other rounding)
    late4, adopted = flat(spec.config(sooner.LEVERS["round-2+late-epochs-4"], 0)), flat(spec.config(sooner.LEVERS["adopted"], 0))
    assert {k for k in adopted if late4[k] != adopted[k]} == {"train.cpu_fusion_emitters"}
    assert (late4["train.cpu_fusion_emitters"], adopted["train.cpu_fusion_emitters"]) == ("legacy", "new")
    # ... and the recorded runs it is paired with (sooner_lr6_decay96_10M.json, seed 0) keep their identity
    full = study.Study("cpu-quick", 10_000_000, (0,), "unused")
    assert evaluation.config_identity(full.config(sooner.ROUND_2, 0)) == "e15bf1772faa0ce7"
    changes_only_what_it_names(round_2, sooner._OVER_ROUND_2, "round-2+")  # the third round's levers
    assert sooner.main(["--variants", "adopted", "--reference", "nope", "--runs-dir", "unused"]) == 2
    assert "--reference 'nope' is not a variant here" in capsys.readouterr().err
    assert sooner.main(["--seeds", "0-", "--runs-dir", "unused"]) == 2
    assert sooner.main(["--variants", "baseline,bogus", "--runs-dir", "unused"]) == 2
    assert "unknown variant(s) bogus" in capsys.readouterr().err


def test_a_screen_trains_into_the_full_schedule_and_resume_finishes_the_group(
        tmp_path: pytest.TempPathFactory, capsys: pytest.CaptureFixture) -> None:
    """``--screen-steps`` trains a variant's seeds as a group only to the cycle that holds N env steps of the full
    budget's schedule (checkpointed, no policy, no evaluation) and reports time to each level within them; the
    same screen again trains nothing; the study without it and with ``--resume`` continues the group to the end
    and evaluates it.  A screen at or beyond the budget exits 2."""
    out, runs = str(tmp_path / "screen.json"), str(tmp_path / "runs")
    common = ["experiments.sooner", "--preset", "cpu-quick", "--total-steps", "8192", "--seeds", "2", "--variants",
              "adopted", "--eval-episodes", "8", "--blocking-episodes", "0", "--runs-dir", runs, "--no-progress",
              "--no-figures", *_sets(TINY_SETS)]
    res = _run(common + ["--screen-steps", "3000", "--out", out])  # 1,024 env steps an iteration, 2 a cycle
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert "training seeds 0, 1 as one group" in res.stdout
    with open(out, encoding="utf-8") as f:
        screen = json.load(f)
    assert screen["screen_steps"] == 3000 and screen["total_steps"] == 8192
    rows = screen["screen"]["adopted"]["per_seed"]
    assert [r["seed"] for r in rows] == [0, 1] and all(r["horizon"] == 4096 for r in rows)
    assert set(screen["screen"]["adopted"]["reached"]) == {"env_steps_to_90", "env_steps_to_95", "env_steps_to_98",
                                                           "env_steps_to_99"}
    for seed in (0, 1):
        folder = os.path.join(runs, "adopted", f"seed{seed}")
        assert study.run_state(folder) == "partial" and study.trained_steps(folder) == 4096
        assert not os.path.exists(os.path.join(folder, compare.RESULT_FILE))
    from experiments import sooner  # what trains nothing runs in process

    assert sooner.main(common[1:] + ["--screen-steps", "3000", "--out", out]) == 0
    again = capsys.readouterr().out
    assert "training" not in again and "resuming" not in again and "| adopted | median |" in again
    assert sooner.main(common[1:] + ["--screen-steps", "8192", "--out", out]) == 2
    assert "--screen-steps 8192: give 1 <= N < the budget" in capsys.readouterr().err
    assert sooner.main(common[1:] + ["--out", out]) == 2  # the screened runs stopped before the budget
    assert "pass --resume" in capsys.readouterr().err
    full = _run(common + ["--resume", "--out", str(tmp_path / "full.json")])
    assert full.returncode == 0, full.stdout[-3000:] + full.stderr[-3000:]
    assert "resuming seeds 0, 1 as one group" in full.stdout
    for seed in (0, 1):
        folder = os.path.join(runs, "adopted", f"seed{seed}")
        assert study.run_state(folder) == "trained" and study.trained_steps(folder) == 8192


def test_failures_counts_each_kind_of_failed_episode_over_seeds(tmp_path: pytest.TempPathFactory,
                                                                   capsys: pytest.CaptureFixture) -> None:
    def group(n: int, success: float, timeout: float, **parts: float) -> dict:
        return {"episodes": n, "success_rate": success, "timeout_rate": timeout,
                "collision_rate": sum(parts.values()), "collision_by": parts}

    run = {"conditions": {"robot": {"obstacle_present": group(200, 0.95, 0.02, obstacle=0.02, target=0.01),
                                    "obstacle_absent": group(800, 0.99, 0.01)}},
           "blocking_scenes": {"blocking": group(1000, 0.97, 0.005, obstacle=0.02, table=0.005)}}
    rows = compare.failures_table({"runs": {"v": [run, run]}}, "robot")["v"]
    assert rows["obstacle"] == {"episodes": 400, "failed": 20, "timeout": 8, "obstacle": 8, "table": 0, "target": 4,
                                "other": 0}
    assert rows["no obstacle"]["failed"] == 16 and rows["no obstacle"]["timeout"] == 16
    assert rows["blocking scenes (own env)"]["obstacle"] == 40 and rows["blocking scenes (own env)"]["table"] == 10
    path = tmp_path / "r.json"
    path.write_text(json.dumps({"runs": {"v": [run]}}))
    assert compare.main(["failures", str(path), "--condition", "dynamic"]) == 2 and "no 'dynamic'" in capsys.readouterr().err
    assert compare.main(["failures", str(path), "--condition", "robot"]) == 0
    assert "| v, obstacle | 200 | 10 | 4 | 4 | 2 | 0 | 0 |" in capsys.readouterr().out


def test_reference_from_an_earlier_result_is_checked_before_anything_trains(
        tmp_path: pytest.TempPathFactory, capsys: pytest.CaptureFixture) -> None:
    """``--reference-from`` reuses an earlier study's reference rows only if they were measured the same way
    (each seed's config identity, evaluation episodes, conditions, seeds); anything else exits 2 naming the
    difference, before a run is trained (the runs folder stays absent)."""
    from experiments import sooner
    from sagrasp_jax.training import evaluation

    spec = study.Study("cpu-quick", 3_000_000, (0, 1), "unused")
    runs_rec = [{"seed": s, "conditions": {},
                 "mix": {"config_sha256": evaluation.config_identity(spec.config(sooner.LEVERS["baseline"], s))}}
                for s in (0, 1)]
    recorded = {"eval_episodes": 1000, "blocking_episodes": 0, "runs": {"baseline": runs_rec},
                "summary": {"baseline": {"seeds": [0, 1], "per_seed": [{"seed": 0}, {"seed": 1}]}}}
    good = tmp_path / "old.json"
    good.write_text(json.dumps(recorded))
    args = compare.parse_args(["--preset", "cpu-quick", "--seeds", "2", "--total-steps", "3000000",
                               "--blocking-episodes", "0", "--reference-from", str(good)], "sooner")
    spec = study.study_from_args(args)
    assert compare.recorded_reference(args, spec, sooner.LEVERS, "baseline", {"epochs-8": ()})["from"] == str(good)
    with pytest.raises(study.StudyError, match="both trained here"):
        compare.recorded_reference(args, spec, sooner.LEVERS, "baseline", {"baseline": ()})
    runs = tmp_path / "runs"
    common = ["--variants", "epochs-8", "--runs-dir", str(runs), "--no-progress", "--reference-from"]
    cases = [(["--seeds", "2", "--total-steps", "3000000", "--reference-from", str(tmp_path / "absent.json")],
              "cannot read it"),
             (["--seeds", "3", "--total-steps", "3000000"], "seeds [0, 1] (here [0, 1, 2])"),
             (["--seeds", "2", "--total-steps", "3000000", "--blocking-episodes", "1000"], "blocking_episodes 0"),
             (["--seeds", "2", "--total-steps", "3000000", "--condition", "robot"], "conditions [] (here ['robot'])"),
             (["--seeds", "2", "--total-steps", "3000000", "--set", "ppo.num_epochs=2"], "another config"),
             (["--seeds", "2", "--total-steps", "2000000"], "another config")]
    for extra, message in cases:
        assert sooner.main(common + [str(good)] + extra) == 2, extra
        assert message in capsys.readouterr().err, extra
    assert not runs.exists()


# ---------------------------------------------------------------------- obstacle ablation

def _ablation_record(seed: int, overall: float, obstacle: float, blocking: float) -> dict:
    group = lambda rate, n=100: {"episodes": n, "success_rate": rate, "collision_rate": 1.0 - rate,  # noqa: E731
                                 "mean_steps_per_success": 24.0, "collision_by": {"obstacle": 1.0 - rate}}
    blind = {"seeing_minus_blind": 0.1}
    return {"seed": seed, "mix": {"overall": group(overall), "obstacle_present": group(obstacle),
                                  "blocking": group(blocking, 10), "obstacle_absent": group(overall)},
            "blocking_scenes": {"blocking": group(blocking)}, "blind": {"obstacle": blind, "blocking": blind},
            "train_time_s": 100.0}


def test_obstacle_ablation_variants_and_overrides() -> None:
    names = ab.variants(leave_one_out=True)
    assert names["base"] == set() and names["all"] == set(ab.LEVERS) and names["+mix"] == {"mix"}
    assert names["all-critic"] == set(ab.LEVERS) - {"critic"} and len(names) == 2 + 2 * len(ab.LEVERS)
    on = ab.overrides_for({"layout"})
    assert "env.task.obs_layout=relative" in on and "env.reward.near_miss_mode=per_step" in on
    assert len(on) == sum(len(ab.LEVERS[k][1]) for k in ab.LEVERS)  # every lever pinned, on or off


def test_obstacle_ablation_summary_counts_runs_that_never_learned() -> None:
    records = [_ablation_record(0, 0.98, 0.90, 0.80), _ablation_record(1, 0.004, 0.02, 0.04),
               _ablation_record(2, 0.96, 0.86, 0.70)]
    s = ab.summarise(records)
    assert s["success_overall"]["mean"] == pytest.approx((98.0 + 0.4 + 96.0) / 3)
    assert s["runs_learned"] == {"learned": 2, "runs": 3, "threshold_pct": ab.LEARNED}
    assert s["learned_only"]["success_obstacle"]["mean"] == pytest.approx(88.0)  # seed 1 (hovering) left out
    assert s["collision_by_in_obstacle_episodes"]["obstacle"]["mean"] == pytest.approx((10 + 98 + 14) / 3)
    table = ab.markdown({"v": s})
    assert "| v | 2 of 3 | 97.0" in table


def test_readme_line_reads_xla_compile_options() -> None:
    """``readme_line options --option KEY=VALUE`` hands XLA typed values (a bool option refuses the text 'false'),
    and a malformed item is named."""
    from experiments import readme_line

    assert readme_line.parse_options(["xla_backend_optimization_level=1", "xla_cpu_enable_fast_math=false",
                                      "xla_cpu_max_isa=AVX2"]) == {
        "xla_backend_optimization_level": 1, "xla_cpu_enable_fast_math": False, "xla_cpu_max_isa": "AVX2"}
    with pytest.raises(SystemExit, match="'xla_backend_optimization_level': expected KEY=VALUE"):
        readme_line.parse_options(["xla_backend_optimization_level"])


def test_readme_line_times_the_readmes_own_first_command() -> None:
    """experiments.readme_line runs the README's first bash line as written: the install, the training and the
    evaluation the README promises, in that order."""
    from experiments import readme_line

    line = readme_line.readme_line(os.path.join(REPO, "README.md"))
    parts = [part.strip() for part in line.split("&&")]
    assert parts[0] == "python3 -m venv .venv" and parts[2].startswith("pip install") \
        and parts[2].endswith('-e ".[train]"')
    assert parts[3].startswith("python -m sagrasp_jax.train --preset cpu-quick") and "--out runs/quick" in parts[3]
    assert parts[4].startswith("python -m sagrasp_jax.evaluate --run runs/quick")
