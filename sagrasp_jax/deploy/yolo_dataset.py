"""Labelled images for the YOLO option: ``python -m sagrasp_jax.deploy.yolo_dataset --out DIR --images N``.

    python -m sagrasp_jax.deploy.yolo_dataset --out DIR --images N [--seed S] [--resolution F]
        [--val-fraction F] [--obstacle-prob P] [--blocking-prob P] [--kinds KIND,KIND,...]
        [--arm-visible-prob P]

Renders N scenes drawn by the training sampler (``sampling.sample_reset``: the target region, every
obstacle kind of ``--kinds`` (default every registered kind), blocking placements) with the twin camera
(``deploy.twin_camera``: the Mech-Eye's optics at ``--resolution`` × 1920 × 1200), each with domain-randomised colours (target
red-ish, obstacles light, table any muted colour) and lighting (direction, warmth, strength, shadows),
the arm in view (at its start pose) in a share ``--arm-visible-prob`` of them.  Writes the Ultralytics
YOLO layout::

    DIR/images/{train,val}/000000.png   RGB
    DIR/labels/{train,val}/000000.txt   one "class x_centre y_centre width height" line per visible object
    DIR/dataset.yaml                    path, train, val, names (``deploy.yolo.classes()``: target + shapes.NAMES)

A box is the object's visible pixels (the render's segmentation), normalised to the image; an object
with fewer than ``MIN_PIXELS`` visible pixels gets none.  Every file is written atomically and
dataset.yaml last: a folder without it is unfinished.  Exit status 2, nothing written, for a bad option
or an ``--out`` folder that is not empty.  Needs the ``twin`` extra (PyBullet); not ultralytics.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import struct
import sys
import time
import zlib
from typing import Sequence

import numpy as np

from sagrasp_jax.base import cli
from sagrasp_jax.base import extras

MIN_PIXELS = 12  # visible pixels an object needs to be labelled


def png_bytes(rgb: np.ndarray) -> bytes:
    """An (H, W, 3) uint8 image as PNG (zlib only: no imaging library needed)."""
    image = np.ascontiguousarray(rgb, dtype=np.uint8)
    h, w = image.shape[:2]
    raw = np.concatenate([np.zeros((h, 1), np.uint8), image.reshape(h, w * 3)], axis=1).tobytes()

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")


def yolo_labels(segmentation: np.ndarray, bodies: Sequence[tuple[int, int]], min_pixels: int = MIN_PIXELS) -> list[str]:
    """YOLO label lines for ``bodies`` (PyBullet body id, class id) from a segmentation (H, W) of body ids."""
    h, w = segmentation.shape
    lines = []
    for body, cls in bodies:
        rows, cols = np.nonzero(segmentation == body)
        if len(rows) < min_pixels:
            continue
        u0, u1, v0, v1 = cols.min(), cols.max() + 1, rows.min(), rows.max() + 1
        lines.append(f"{cls} {(u0 + u1) / 2 / w:.6f} {(v0 + v1) / 2 / h:.6f} {(u1 - u0) / w:.6f} {(v1 - v0) / h:.6f}")
    return lines


def _parser() -> argparse.ArgumentParser:
    p = cli.Parser(prog="python -m sagrasp_jax.deploy.yolo_dataset", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 2)[2])
    p.add_argument("--out", required=True, help="dataset folder to create (must be absent or empty)")
    p.add_argument("--images", type=int, required=True, help="number of images")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resolution", type=float, default=0.25, help="fraction of 1920 × 1200 (default 0.25: 480 × 300)")
    p.add_argument("--val-fraction", type=float, default=0.1, help="share of images for validation (default 0.1)")
    p.add_argument("--obstacle-prob", type=float, default=0.8, help="share of scenes with obstacles (default 0.8)")
    p.add_argument("--blocking-prob", type=float, default=0.3, help="share of obstacle scenes with blocking placement")
    p.add_argument("--kinds", default=None, help="obstacle kinds, comma-separated (default: every registered kind, "
                   "shapes.NAMES)")
    p.add_argument("--arm-visible-prob", type=float, default=0.5, help="share of images with the arm in view")
    return p


def _kinds(args: argparse.Namespace) -> tuple[str, ...]:
    """--kinds as names; unset: every registered kind."""
    from sagrasp_jax.task import shapes

    return shapes.NAMES if args.kinds is None else tuple(k.strip() for k in args.kinds.split(",") if k.strip())


def _check(args: argparse.Namespace) -> list[str]:
    from sagrasp_jax.task import shapes

    problems = []
    if not 1 <= args.images <= 1_000_000:
        problems.append(f"--images {args.images} must be in [1, 1000000]")
    if not (math.isfinite(args.resolution) and 0.05 <= args.resolution <= 1.0):
        problems.append(f"--resolution {args.resolution} must be in [0.05, 1]")
    for name in ("val_fraction", "obstacle_prob", "blocking_prob", "arm_visible_prob"):
        value = getattr(args, name)
        if not (math.isfinite(value) and 0.0 <= value <= 1.0):
            problems.append(f"--{name.replace('_', '-')} {value} must be in [0, 1]")
    kinds = _kinds(args)
    unknown = [k for k in kinds if k not in shapes.BY_NAME]
    if unknown or not kinds:
        problems.append(f"--kinds {args.kinds!r}: each must be one of {', '.join(shapes.NAMES)}")
    if os.path.exists(args.out) and (not os.path.isdir(args.out) or os.listdir(args.out)):
        problems.append(f"--out {args.out} exists and is not an empty folder")
    return problems


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    prog = "python -m sagrasp_jax.deploy.yolo_dataset"
    problems = _check(args)
    if problems:
        print(f"{prog}: error: " + "; ".join(problems), file=sys.stderr)
        return 2
    extras.require_cli("twin", prog=prog)
    from sagrasp_jax.task import robot
    from sagrasp_jax.task import sampling
    from sagrasp_jax.task import shapes
    from sagrasp_jax.task.config import EnvConfig, blocking_sampling
    from sagrasp_jax.deploy.twin import PyBulletTwin
    from sagrasp_jax.deploy.twin_camera import TwinCamera, random_colours, random_lighting
    from sagrasp_jax.deploy.yolo import classes
    from sagrasp_jax.base.fileio import NotWritable, atomic_write_bytes, atomic_write_text, check_writable

    try:
        check_writable(args.out, "dataset folder")
    except NotWritable as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    kinds = _kinds(args)
    classes_ = classes()
    cfg = EnvConfig()
    cfg = dataclasses.replace(cfg, sampling=blocking_sampling(
        dataclasses.replace(cfg.sampling, obstacle_kinds=kinds), args.obstacle_prob, args.blocking_prob))
    model = robot.load_robot(cfg.robot)
    rng = np.random.default_rng(args.seed)
    camera = TwinCamera(args.resolution)
    n_val = int(round(args.val_fraction * args.images))
    counts = dict.fromkeys(classes_, 0)
    t0 = time.perf_counter()
    for i in range(args.images):
        split = "val" if i < n_val else "train"
        spec = sampling.sample_reset(np, model, cfg.sampling, cfg.task, rng.random(sampling.uniforms_needed(cfg.sampling, model.dof)))
        with PyBulletTwin(spec, cfg, q0=spec.q0) as twin:
            frame = camera.capture(twin, colours=random_colours(rng, len(twin.obstacle_bodies)),
                                   lighting=random_lighting(rng), hide_robot=bool(rng.random() >= args.arm_visible_prob))
            active = np.nonzero(np.asarray(spec.obstacle_active))[0]
            bodies = [(twin.target_body, 0)] + [
                (body, classes_.index(shapes.BY_ID[int(spec.obstacle_kind[j])].name)) for body, j in zip(twin.obstacle_bodies, active)]
        lines = yolo_labels(frame.segmentation, bodies)
        for line in lines:
            counts[classes_[int(line.split()[0])]] += 1
        name = f"{i:06d}"
        atomic_write_bytes(os.path.join(args.out, "images", split, name + ".png"), png_bytes(frame.rgb))
        atomic_write_text(os.path.join(args.out, "labels", split, name + ".txt"), "".join(f"{ln}\n" for ln in lines))
    yaml = (f"# written by {prog} --images {args.images} --seed {args.seed} --resolution {args.resolution}\n"
            f"path: {os.path.abspath(args.out)}\ntrain: images/train\nval: images/val\nnames:\n"
            + "".join(f"  {i}: {name}\n" for i, name in enumerate(classes_)))
    atomic_write_text(os.path.join(args.out, "dataset.yaml"), yaml)
    print(f"{args.images} images ({args.images - n_val} train, {n_val} val) in {args.out}, "
          f"{time.perf_counter() - t0:.1f} s; labelled objects: " + ", ".join(f"{k} {v}" for k, v in counts.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
