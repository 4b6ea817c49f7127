"""How well does the perception find the cube and the obstacles on the twin camera's renders?

Scenes come from the project's sampler (``sampling.sample_reset``): the paper's evaluation mix (an obstacle
in 20 % of scenes; sphere, cylinder, box) and blocking scenes (every scene has obstacles, placed on the
straight approach path: ``config.blocking_sampling(·, 1, 1)``).  Each scene is built in the PyBullet twin,
captured once by the twin camera (``deploy.twin_camera``: the Mech-Eye's optics at ``--resolution``, the
arm parked out of view unless ``--arm visible``; then the perception is handed its joints), and the clean
cloud is perceived (``deploy.perception.detect_scene``, RGB included) as is and after each depth-noise
model of ``--noise``.  Against the sampled truth it reports, per mix and noise level:

* target: refusals (with their messages), centre error (3-D, p50 / p95 / max), horizontal and vertical
  parts, yaw error (mod 90°);
* obstacles: true ones, in view (≥ ``MIN_VISIBLE_PX`` pixels of it in the render), found (a detection
  within ``MATCH_M`` horizontally), missed, invented (detections matching none), and for the *whole*
  ones (at most ``HIDDEN_TOL`` of the pixels they fill alone, rendered a second time without the other
  objects, hidden behind another object, and clear of the image border) and the *partly hidden* ones
  apart: kind right, centre error (3-D, p50 / p95 / max, share ≤ 5 mm), size error (largest relative
  error of its dimensions, boxes compared in the orientation that matches; share within 10 %), and the
  share found with the right kind, ≤ 5 mm and ≤ 10 % at once.  A single camera cannot measure what a
  floating sphere hides of a box below it: the partly hidden ones show what that costs;
* time: twin build, render, perception (mean, ms).

Prints a table and writes JSON (``--out``).  ~0.25 s per scene and noise level on one core at 480 × 300.

    nice -n 5 python -m experiments.perception_accuracy --scenes 1000 --blocking 500 \\
        --out experiments/results/perception_accuracy.json
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from typing import Any

import numpy as np
import pybullet as pb

from sagrasp_jax.task import robot
from sagrasp_jax.task import sampling
from sagrasp_jax.task import shapes
from sagrasp_jax.task.config import EnvConfig, blocking_sampling
from sagrasp_jax.deploy import perception
from sagrasp_jax.deploy.calibration import CameraCalibration
from sagrasp_jax.deploy.twin import PyBulletTwin
from sagrasp_jax.deploy.twin_camera import NOISE_MODELS, TwinCamera, apply_depth_noise
from sagrasp_jax.base.fileio import atomic_write_json

MATCH_M = 0.05  # a detected obstacle matches a true one whose centre is this near horizontally
MIN_VISIBLE_PX = 30  # an obstacle with fewer visible pixels in the render is not "in view"
SIZE_TOL = 0.10
CENTRE_TOL_M = 0.005
HIDDEN_TOL = 0.05  # an obstacle with more of its pixels hidden by another object (or cut by the border) is "partly hidden"


def size_error(kind: str, true_size: np.ndarray, true_yaw: float, det: perception.Obstacle) -> float:
    """Largest relative error of the obstacle's dimensions (NaN for a wrong kind); a box's half-extents are
    compared in the orientation of the detected yaw that matches (a box turned by 90° swaps them)."""
    if det.kind != kind:
        return math.nan
    got, ref = np.asarray(det.size, float), np.asarray(true_size, float)
    if kind == "sphere":
        return abs(got[0] - ref[0]) / ref[0]
    if kind == "cylinder":
        return max(abs(got[0] - ref[0]) / ref[0], abs(got[1] - ref[1]) / ref[1])
    if kind == "box":
        if abs(perception.wrap(det.yaw - true_yaw, math.pi)) > math.pi / 4:
            got = got[[1, 0, 2]]
        return float(np.max(np.abs(got - ref) / ref))
    if kind == "capsule":  # radius and tip-to-tip length
        return max(abs(got[0] - ref[0]) / ref[0], abs((got[1] + got[0]) - (ref[1] + ref[0])) / (ref[1] + ref[0]))
    raise ValueError(kind)


def match_obstacles(truth: list[dict[str, Any]], found: list[perception.Obstacle]) -> list[tuple[int, int]]:
    """Greedy nearest pairs (true index, detected index) within MATCH_M horizontally."""
    pairs = sorted((float(np.linalg.norm(np.asarray(t["centre"][:2]) - np.asarray(d.centre[:2]))), i, j)
                   for i, t in enumerate(truth) for j, d in enumerate(found))
    used_t, used_d, out = set(), set(), []
    for dist, i, j in pairs:
        if dist <= MATCH_M and i not in used_t and j not in used_d:
            used_t.add(i)
            used_d.add(j)
            out.append((i, j))
    return out


def pixels_alone(twin: PyBulletTwin, camera: TwinCamera, body: int, hide_robot: bool) -> int:
    """Pixels ``body`` would fill with the other obstacles and the cube out of the way (its unoccluded view)."""
    others = [b for b in (twin.target_body, *twin.obstacle_bodies) if b != body]
    poses = [pb.getBasePositionAndOrientation(b, physicsClientId=twin._client) for b in others]
    try:
        for b, (_, orn) in zip(others, poses):
            pb.resetBasePositionAndOrientation(b, [0.0, 0.0, -50.0], orn, physicsClientId=twin._client)
        return int((camera.capture(twin, hide_robot=hide_robot).segmentation == body).sum())
    finally:
        for b, (pos, orn) in zip(others, poses):
            pb.resetBasePositionAndOrientation(b, pos, orn, physicsClientId=twin._client)


def scene_truth(spec: sampling.ResetSpec, twin: PyBulletTwin, segmentation: np.ndarray, camera: TwinCamera,
                hide_robot: bool) -> list[dict[str, Any]]:
    """The active obstacles with how much of each the capture shows: its pixels, the pixels it would fill
    alone (a second render without the other objects, when there are any), whether it touches the border."""
    active = np.nonzero(np.asarray(spec.obstacle_active))[0]
    h, w = segmentation.shape
    out = []
    for body, j in zip(twin.obstacle_bodies, active):
        rows, cols = np.nonzero(segmentation == body)
        alone = pixels_alone(twin, camera, body, hide_robot) if len(active) > 1 else int(len(rows))
        out.append({"kind": shapes.BY_ID[int(spec.obstacle_kind[j])].name, "centre": np.asarray(spec.obstacle_pos[j], float),
                    "size": np.asarray(spec.obstacle_size[j], float), "yaw": float(spec.obstacle_yaw[j]),
                    "pixels": int(len(rows)), "hidden_share": 1.0 - len(rows) / alone if alone else 1.0,
                    "border": bool(len(rows) and (rows.min() == 0 or cols.min() == 0 or rows.max() == h - 1 or cols.max() == w - 1))})
    return out


def evaluate_scene(spec: sampling.ResetSpec, truth: list[dict[str, Any]], cloud: np.ndarray, rgb: np.ndarray,
                   cal: CameraCalibration, robot_q: Any) -> dict[str, Any]:
    t0 = time.perf_counter()
    try:
        det = perception.detect_scene(cloud, rgb, cal, robot_q=robot_q)
    except perception.PerceptionError as exc:
        return {"refused": str(exc), "perception_s": time.perf_counter() - t0, "obstacles": []}
    seconds = time.perf_counter() - t0
    err = det.target_centre - np.asarray(spec.target_pos, float)
    rec: dict[str, Any] = {
        "refused": None, "perception_s": seconds, "target_err_m": float(np.linalg.norm(err)),
        "target_err_xy_m": float(np.linalg.norm(err[:2])), "target_err_z_m": float(err[2]),
        "yaw_err_deg": abs(math.degrees(perception.wrap(det.target_yaw - float(spec.target_yaw), math.pi / 2))),
        "detected": len(det.obstacles), "obstacles": [],
    }
    pairs = dict(match_obstacles(truth, det.obstacles))
    for i, t in enumerate(truth):
        entry = {"kind": t["kind"], "pixels": t["pixels"], "hidden_share": t["hidden_share"], "border": t["border"],
                 "found": i in pairs}
        if i in pairs:
            d = det.obstacles[pairs[i]]
            size = size_error(t["kind"], t["size"], t["yaw"], d)
            entry.update(found_kind=d.kind, centre_err_m=float(np.linalg.norm(np.asarray(d.centre) - t["centre"])),
                         size_err=None if math.isnan(size) else size, found_size=list(d.size), found_yaw=d.yaw,
                         true_size=t["size"].tolist(), true_yaw=t["yaw"], centre=t["centre"].tolist())
        rec["obstacles"].append(entry)
    rec["invented"] = len(det.obstacles) - len(pairs)
    matched = set(pairs.values())
    rec["invented_detail"] = [{"kind": d.kind, "centre": list(d.centre), "size": list(d.size)}
                              for j, d in enumerate(det.obstacles) if j not in matched]
    return rec


def _pct(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def obstacle_stats(obs: list[dict[str, Any]]) -> dict[str, Any]:
    """Found share, kind, centre and size errors of true obstacles (entries of ``evaluate_scene``)."""
    found = [o for o in obs if o["found"]]
    centre = [1000 * o["centre_err_m"] for o in found]
    size = [o["size_err"] for o in found]
    good = [o for o in found if o["found_kind"] == o["kind"] and o["centre_err_m"] <= CENTRE_TOL_M
            and o["size_err"] is not None and o["size_err"] <= SIZE_TOL]
    return {
        "count": len(obs), "found": len(found), "missed": len(obs) - len(found),
        "found_share": len(found) / len(obs) if obs else None,
        "found_right_share": len(good) / len(obs) if obs else None,
        "kind_right_share": sum(o["found_kind"] == o["kind"] for o in found) / len(found) if found else None,
        "centre_err_mm": {"p50": _pct(centre, 50), "p95": _pct(centre, 95), "max": max(centre) if centre else None},
        "centre_within_5mm_share": sum(c <= 1000 * CENTRE_TOL_M for c in centre) / len(centre) if centre else None,
        "size_err": {"p50": _pct([s for s in size if s is not None], 50), "p95": _pct([s for s in size if s is not None], 95)},
        "size_within_10pct_share": sum(s is not None and s <= SIZE_TOL for s in size) / len(size) if size else None,
    }


def summarise(records: list[dict[str, Any]]) -> dict[str, Any]:
    ok = [r for r in records if r["refused"] is None]
    errs = [1000 * r["target_err_m"] for r in ok]
    obs = [o for r in records for o in r["obstacles"]]
    in_view = [o for o in obs if o["pixels"] >= MIN_VISIBLE_PX]
    found = [o for o in in_view if o["found"]]
    centre = [1000 * o["centre_err_m"] for o in found]
    size = [o["size_err"] for o in found]
    detected = sum(r.get("detected", 0) for r in ok)
    invented = sum(r.get("invented", 0) for r in ok)
    whole = [o for o in in_view if o["hidden_share"] <= HIDDEN_TOL and not o["border"]]
    refusals: dict[str, int] = {}
    for r in records:
        if r["refused"]:
            key = r["refused"].split(":")[0].split("(")[0].strip()
            refusals[key] = refusals.get(key, 0) + 1
    return {
        "scenes": len(records), "refused": len(records) - len(ok), "refusals": refusals,
        "target_err_mm": {"p50": _pct(errs, 50), "p95": _pct(errs, 95), "max": max(errs) if errs else None},
        "target_err_xy_mm_p95": _pct([1000 * r["target_err_xy_m"] for r in ok], 95),
        "target_err_z_mm_p95": _pct([1000 * abs(r["target_err_z_m"]) for r in ok], 95),
        "yaw_err_deg": {"p50": _pct([r["yaw_err_deg"] for r in ok], 50), "p95": _pct([r["yaw_err_deg"] for r in ok], 95)},
        "obstacles": {
            "true": len(obs), "in_view": len(in_view), "found": len(found), "missed": len(in_view) - len(found),
            "found_share": len(found) / len(in_view) if in_view else None,
            "found_of_all_true": sum(o["found"] for o in obs) / len(obs) if obs else None,
            "detected": detected, "invented": invented, "invented_share": invented / detected if detected else None,
            "kind_right_share": sum(o["found_kind"] == o["kind"] for o in found) / len(found) if found else None,
            "centre_err_mm": {"p50": _pct(centre, 50), "p95": _pct(centre, 95), "max": max(centre) if centre else None},
            "centre_within_5mm_share": sum(c <= 1000 * CENTRE_TOL_M for c in centre) / len(centre) if centre else None,
            "size_err": {"p50": _pct([s for s in size if s is not None], 50),
                         "p95": _pct([s for s in size if s is not None], 95)},
            "size_within_10pct_share": sum(s is not None and s <= SIZE_TOL for s in size) / len(size) if size else None,
            "found_right_share": obstacle_stats(in_view)["found_right_share"],
            "whole": obstacle_stats(whole),
            "partly_hidden": obstacle_stats([o for o in in_view if o not in whole]),
            "by_kind": {k: {"in_view": sum(o["kind"] == k for o in in_view), "found": sum(o["kind"] == k for o in found),
                            "kind_right": sum(o["kind"] == k and o["found_kind"] == k for o in found)}
                        for k in sorted({o["kind"] for o in obs})},
        },
        "perception_ms_mean": 1000 * float(np.mean([r["perception_s"] for r in records])) if records else None,
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    levels = [n.strip() for n in args.noise.split(",") if n.strip()]
    for n in levels:
        if n not in NOISE_MODELS:
            raise SystemExit(f"unknown --noise {n!r}; known: {', '.join(NOISE_MODELS)}")
    base = EnvConfig()
    mixes = {"paper": base, "blocking": dataclasses.replace(base, sampling=blocking_sampling(base.sampling, 1.0, 1.0))}
    counts = {"paper": args.scenes, "blocking": args.blocking}
    model = robot.load_robot()
    cal = CameraCalibration.default()
    camera = TwinCamera(args.resolution)
    results: dict[str, Any] = {"settings": {**vars(args), "intrinsics": dataclasses.asdict(camera.intrinsics),
                                            "noise_models": {n: dataclasses.asdict(NOISE_MODELS[n]) for n in levels}},
                               "summary": {}, "timing_ms": {}}
    for mix, cfg in mixes.items():
        rng = np.random.default_rng([args.seed, list(mixes).index(mix)])
        records: dict[str, list[dict[str, Any]]] = {n: [] for n in levels}
        build_s, render_s = [], []
        for i in range(counts[mix]):
            spec = sampling.sample_reset(np, model, cfg.sampling, cfg.task, rng.random(sampling.uniforms_needed(cfg.sampling)))
            t0 = time.perf_counter()
            with PyBulletTwin(spec, cfg, q0=spec.q0) as twin:
                build_s.append(time.perf_counter() - t0)
                frame = camera.capture(twin, hide_robot=args.arm == "hidden")
                render_s.append(frame.render_s)
                truth = scene_truth(spec, twin, frame.segmentation, camera, args.arm == "hidden")
            for k, level in enumerate(levels):
                noisy = apply_depth_noise(frame.cloud_mm, level, np.random.default_rng([args.seed, i, k, len(mix)]))
                rec = evaluate_scene(spec, truth, noisy, frame.rgb, cal, None if args.arm == "hidden" else spec.q0)
                rec["scene"] = i
                records[level].append(rec)
            if (i + 1) % 100 == 0:
                print(f"  {mix}: {i + 1}/{counts[mix]} scenes", file=sys.stderr, flush=True)
        results["summary"][mix] = {n: summarise(records[n]) for n in levels}
        results["timing_ms"][mix] = {"twin_build": 1000 * float(np.mean(build_s)) if build_s else None,
                                     "render": 1000 * float(np.mean(render_s)) if render_s else None}
        results.setdefault("refusal_examples", {})[mix] = {
            n: [{"scene": r["scene"], "message": r["refused"]} for r in records[n] if r["refused"]][:10] for n in levels}
        results.setdefault("worst_obstacles", {})[mix] = {
            n: sorted(({"scene": r["scene"], **o} for r in records[n] for o in r["obstacles"]
                       if o.get("found") and (o.get("found_kind") != o["kind"] or (o.get("size_err") or 0) > SIZE_TOL
                                              or o.get("centre_err_m", 0) > CENTRE_TOL_M)),
                      key=lambda o: -o.get("centre_err_m", 0))[:10] for n in levels}
        results.setdefault("invented_examples", {})[mix] = {
            n: [{"scene": r["scene"], **d} for r in records[n] for d in r.get("invented_detail", [])][:10] for n in levels}
    return results


def _fmt(v: Any, scale: float = 1.0, digits: int = 2) -> str:
    return "—" if v is None else f"{v * scale:.{digits}f}"


def table(results: dict[str, Any]) -> str:
    """Markdown: the target's errors, then the obstacles (all in view; whole ones: errors; partly hidden ones)."""
    lines = ["| mix | noise | scenes | refused | target centre p50 / p95 / max (mm) | yaw p95 (°) | obstacles in view "
             "(whole + partly hidden) | found | invented | whole: kind right | centre p50 / p95 / max (mm) | ≤ 5 mm "
             "| size p95 | size ≤ 10 % | kind, ≤ 5 mm and ≤ 10 % | partly hidden: found | kind, ≤ 5 mm and ≤ 10 % |",
             "|" + "---|" * 17]
    for mix, by_level in results["summary"].items():
        for level, s in by_level.items():
            t, o = s["target_err_mm"], s["obstacles"]
            w, p = o["whole"], o["partly_hidden"]
            lines.append(
                f"| {mix} | {level} | {s['scenes']} | {s['refused']} | {_fmt(t['p50'])} / {_fmt(t['p95'])} / {_fmt(t['max'])} "
                f"| {_fmt(s['yaw_err_deg']['p95'], digits=1)} | {o['in_view']} ({w['count']} + {p['count']}) "
                f"| {_fmt(o['found_share'], 100, 1)} % | {o['invented']} ({_fmt(o['invented_share'], 100, 2)} %) "
                f"| {_fmt(w['kind_right_share'], 100, 1)} % "
                f"| {_fmt(w['centre_err_mm']['p50'])} / {_fmt(w['centre_err_mm']['p95'])} / {_fmt(w['centre_err_mm']['max'])} "
                f"| {_fmt(w['centre_within_5mm_share'], 100, 1)} % | {_fmt(w['size_err']['p95'], 100, 1)} % "
                f"| {_fmt(w['size_within_10pct_share'], 100, 1)} % | {_fmt(w['found_right_share'], 100, 1)} % "
                f"| {_fmt(p['found_share'], 100, 1)} % | {_fmt(p['found_right_share'], 100, 1)} % |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=1000, help="scenes of the paper's mix")
    parser.add_argument("--blocking", type=int, default=500, help="blocking scenes")
    parser.add_argument("--noise", default="none,industrial,consumer", help="depth-noise models, comma-separated")
    parser.add_argument("--resolution", type=float, default=0.25, help="fraction of the Mech-Eye's 1920 × 1200")
    parser.add_argument("--arm", choices=("hidden", "visible"), default="hidden",
                        help="hidden: the arm parked out of view for the capture; visible: at its start pose, "
                             "the perception given its joints")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="experiments/results/perception_accuracy.json")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    results = run(args)
    results["wall_s"] = time.perf_counter() - t0
    print(table(results))
    for mix, by_level in results["timing_ms"].items():
        if by_level["render"] is None:
            continue
        print(f"{mix}: twin build {by_level['twin_build']:.0f} ms, render {by_level['render']:.0f} ms per scene; "
              + ", ".join(f"perception ({n}) {s['perception_ms_mean']:.0f} ms" for n, s in results["summary"][mix].items()))
    atomic_write_json(args.out, results, default=float)
    print(f"wrote {args.out} ({results['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
