"""Traps for ``confident``: clutter, units, mirror images, other objects and shapes with no unique pose.

    python scripts/bench_trust.py                          # every scan pair found and the shape traps
    python scripts/bench_trust.py --scans bunny --out outputs/bench_trust.json

Each real scan pair (the Stanford Bunny range scans ``bun045`` -> ``bun000`` with the lab's
``bun.conf``, the GeoTransformer 3DMatch demo pair with its published pose refined onto the whole
fragment 0 (:mod:`scripts.studies.check_3dmatch_ground_truth`: the published pose is 0.76 degrees
and 8.4 cm from where the fragments align), the FRICP statue pair with FRICP's estimate) is
registered by ``linereg.register`` as it is and with its target changed: in other units (x1000,
x0.001, x2, x0.5: rigidly, then with ``scale=True``), mirrored, replaced by another object (the
Stanford Dragon, sampled from its mesh; the statue pair is itself a scan of the Bunny), every
point duplicated, the source cut to the part that does not overlap the target, heavy noise (3 point
spacings), 50-95 % uniform clutter in the target's bounding box, and the target placed in a room
(the 3DMatch demo pair's reference fragment, scaled to 20 times its diameter). The shape traps register two
samplings of a plane, a line, a sphere and a box (symmetric), whose poses are not unique.

An answer is right within 5 degrees and 5 % of the target's diameter (with ``scale=True`` also
within 1 % of the scale; its rotation's distance from the answer on the pair as it is shows what
``scale=True`` costs apart from the label's own error); a trap without a right answer (mirror,
another object, other units solved rigidly, a shape with no unique pose) counts every answer wrong. The table gives each
answer's error, ``confident`` and the first warning; the last line counts answers that are
confident and wrong, which must be none.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import linereg
from linereg.datasets.formats import read_conf
from linereg.io import read_point_cloud, read_transform
from linereg.paths import shared_data_dir
from linereg.registration.poses import rotation_gap_deg
from linereg.registration.trust import spacing_of
from scripts.studies.check_3dmatch_ground_truth import refined_demo_pose

RIGHT_DEG = 5.0
RIGHT_SHARE = 0.05
RIGHT_SCALE = 0.01
CLUTTER = (0.5, 0.8, 0.9, 0.95)
UNITS = (1000.0, 0.001, 2.0, 0.5)


class Pair(NamedTuple):
    """Source, target and the source-to-target truth (``None``: no transform is right)."""

    source: np.ndarray
    target: np.ndarray
    truth: np.ndarray | None


def _bunny(data: Path) -> Pair:
    folder = data / "scans/stanford_bunny_range"
    poses = read_conf(folder / "bun.conf")
    truth = np.linalg.inv(poses["bun000.ply"]) @ poses["bun045.ply"]
    return Pair(read_point_cloud(folder / "bun045.ply").xyz, read_point_cloud(folder / "bun000.ply").xyz, truth)


def _demo(data: Path) -> Pair:
    folder = data / "3dmatch/geotransformer_demo/demo"
    return Pair(np.load(folder / "src.npy"), np.load(folder / "ref.npy"), refined_demo_pose(data))


def _statue(data: Path) -> Pair:
    folder = data / "scans/fricp_statue"
    truth = read_transform(folder / "m3trans.txt")
    return Pair(read_point_cloud(folder / "source.ply").xyz, read_point_cloud(folder / "target.ply").xyz, truth)


SCANS: dict[str, Callable[[Path], Pair]] = {"bunny": _bunny, "3dmatch": _demo, "statue": _statue}


def _dragon(data: Path, rng: np.random.Generator, count: int = 20000) -> np.ndarray:
    """``count`` points of the Stanford Dragon's surface (the other object)."""
    import trimesh

    from linereg.io import read_mesh

    points, _ = trimesh.sample.sample_surface(
        read_mesh(data / "meshes/stanford_lowres/dragon.ply"), count, seed=int(rng.integers(1 << 31))
    )
    return np.asarray(points, dtype=np.float64)


def _moved(points: np.ndarray, transform: np.ndarray) -> np.ndarray:
    return points @ transform[:3, :3].T + transform[:3, 3]


def _diameter(points: np.ndarray) -> float:
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def scan_traps(
    pair: Pair, other: np.ndarray, room: np.ndarray | None, rng: np.random.Generator
) -> dict[str, tuple[Pair, dict]]:
    """``{trap: (pair, register keyword arguments)}`` of one real scan pair; ``other`` is another
    object's scan, ``room`` a room scan to place the target in (``None``: no such trap)."""
    src, tgt, truth = pair
    spacing = spacing_of(tgt)
    low, high = tgt.min(axis=0), tgt.max(axis=0)
    traps: dict[str, tuple[Pair, dict]] = {"as it is": (pair, {})}
    for factor in UNITS:
        traps[f"target x{factor:g}"] = (Pair(src, factor * tgt, None), {})
        scaled = np.diag([factor, factor, factor, 1.0]) @ truth
        traps[f"target x{factor:g}, scale=true"] = (Pair(src, factor * tgt, scaled), {"scale": True})
    traps["mirrored target"] = (Pair(src, tgt * [-1.0, 1.0, 1.0], None), {})
    fitted = (other - other.mean(axis=0)) * (_diameter(tgt) / _diameter(other)) + tgt.mean(axis=0)
    traps["another object"] = (Pair(src, fitted, None), {})
    traps["duplicated points"] = (Pair(src, np.repeat(tgt, 2, axis=0), truth), {})
    distances = np.min(
        np.stack([np.linalg.norm(_moved(src, truth) - point, axis=1) for point in tgt[:: max(len(tgt) // 2000, 1)]]),
        axis=0,
    )
    apart = src[distances > np.quantile(distances, 0.8)]
    traps["near-zero overlap"] = (Pair(apart, tgt, truth), {})
    traps["heavy noise (3 spacings)"] = (Pair(src, tgt + rng.normal(0.0, 3.0 * spacing, tgt.shape), truth), {})
    for share in CLUTTER:
        clutter = rng.uniform(low, high, (int(len(tgt) * share / (1.0 - share)), 3))
        traps[f"clutter {100 * share:.0f} %"] = (Pair(src, np.concatenate([tgt, clutter]), truth), {})
    if room is not None:
        scene = (room - room.mean(axis=0)) * (20.0 * _diameter(tgt) / _diameter(room)) + tgt.mean(axis=0)
        traps["in a room scan"] = (Pair(src, np.concatenate([tgt, scene]), truth), {})
    return traps


def shape_traps(rng: np.random.Generator, count: int = 8000) -> dict[str, tuple[Pair, dict]]:
    """Two independent samplings of shapes whose pose is not unique (every answer counts wrong)."""

    def plane(offset: float) -> np.ndarray:
        return np.column_stack([rng.uniform(offset, offset + 1.0, (count, 2)), np.zeros(count)])

    def sphere() -> np.ndarray:
        points = rng.normal(size=(count, 3))
        points /= np.linalg.norm(points, axis=1, keepdims=True)
        return points[points[:, 2] > -0.3]

    def line() -> np.ndarray:
        return np.column_stack([rng.uniform(0.0, 1.0, count), rng.normal(0.0, 1e-3, (count, 2))])

    def box() -> np.ndarray:
        sides = np.array([1.0, 1.5, 2.0])
        points = rng.uniform(-0.5, 0.5, (count, 3))
        axis = rng.integers(3, size=count)
        points[np.arange(count), axis] = np.sign(points[np.arange(count), axis]) * 0.5
        return points * sides

    return {
        "plane (two patches)": (Pair(plane(0.0), plane(0.4), None), {}),
        "line": (Pair(line(), line(), None), {}),
        "sphere (two caps)": (Pair(sphere(), sphere(), None), {}),
        "box (symmetric)": (Pair(box(), box(), None), {}),
    }


def judge(pair: Pair, options: dict) -> dict:
    """``register``'s answer on ``pair``: errors, right, confident, warnings, seconds."""
    start = time.perf_counter()
    result = linereg.register(pair.source, pair.target, **options)
    seconds = time.perf_counter() - start
    row = {
        "confident": result.confident,
        "warnings": result.info["warnings"],
        "seconds": seconds,
        "scale": result.scale,
        "rotation": (result.transformation[:3, :3] / result.scale).tolist(),
    }
    if pair.truth is None:
        return {**row, "err_r": None, "err_t": None, "right": False}
    truth_scale = float(np.cbrt(np.linalg.det(pair.truth[:3, :3])))
    rotation = result.transformation[:3, :3] / result.scale
    err_r = float(rotation_gap_deg(rotation[None], pair.truth[:3, :3] / truth_scale)[0])
    err_t = float(np.linalg.norm(result.transformation[:3, 3] - pair.truth[:3, 3])) / _diameter(pair.target)
    scale_error = abs(result.scale / truth_scale - 1.0)
    right = err_r <= RIGHT_DEG and err_t <= RIGHT_SHARE and scale_error <= RIGHT_SCALE
    return {**row, "err_r": err_r, "err_t": err_t, "scale_error": scale_error, "right": right}


def table(rows: list[dict]) -> str:
    lines = [
        "| scan | trap | Err_R (deg) | translation (% diameter) | scale error | vs as it is (deg) | confident "
        "| warning | s |",
        "|---|---|---:|---:|---:|---:|---|---|---:|",
    ]
    for row in rows:
        err = "-" if row["err_r"] is None else f"{row['err_r']:.2f}"
        move = "-" if row["err_t"] is None else f"{100 * row['err_t']:.2f}"
        scale = f"{100 * row['scale_error']:.2f} %" if row.get("scale_error") is not None else "-"
        alike = f"{row['vs_as_it_is']:.2f}" if row.get("vs_as_it_is") is not None else "-"
        warning = row["warnings"][0] if row["warnings"] else "-"
        flag = "**yes, wrong**" if row["confident"] and not row["right"] else ("yes" if row["confident"] else "no")
        lines.append(
            f"| {row['scan']} | {row['trap']} | {err} | {move} | {scale} | {alike} | {flag} | {warning} "
            f"| {row['seconds']:.1f} |"
        )
    wrong = sum(row["confident"] and not row["right"] for row in rows)
    lines.append(f"\nconfident and wrong: {wrong} of {len(rows)} answers")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", nargs="*", default=list(SCANS), choices=list(SCANS))
    parser.add_argument("--shapes", action=argparse.BooleanOptionalAction, default=True, help="the shape traps")
    parser.add_argument("--out", type=Path, default=None, help="also write the rows as JSON")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    data, rng, rows = shared_data_dir() or Path("../shared/data"), np.random.default_rng(args.seed), []
    pairs = {}
    for name in args.scans:
        try:
            pairs[name] = SCANS[name](data)
        except (FileNotFoundError, OSError) as error:
            print(f"bench_trust: {name} skipped: {error}", file=sys.stderr)
    traps = {}
    room = pairs["3dmatch"].target if "3dmatch" in pairs else None
    other = _dragon(data, rng)
    for name, pair in pairs.items():
        scene = room if name != "3dmatch" else None
        traps.update({(name, trap): value for trap, value in scan_traps(pair, other, scene, rng).items()})
    if args.shapes:
        traps.update({("shape", trap): value for trap, value in shape_traps(rng).items()})
    as_it_is = {}
    for (scan, trap), (pair, options) in traps.items():
        row = {"scan": scan, "trap": trap, **judge(pair, options)}
        if trap == "as it is":
            as_it_is[scan] = np.array(row["rotation"])
        elif options.get("scale") and scan in as_it_is:
            gap = rotation_gap_deg(np.array(row["rotation"])[None], as_it_is[scan])
            row["vs_as_it_is"] = float(gap[0])
        rows.append(row)
        print(
            f"{scan} | {trap}: confident {row['confident']}, right {row['right']}, {row['seconds']:.1f} s",
            file=sys.stderr,
        )
    print(table(rows))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
