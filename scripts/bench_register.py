"""Time ``register``: the solver and the whole command, quiet and beside a busy core, against ICP.

    python scripts/bench_register.py                 # 5 partial-vs-whole airplane pairs, 1024 vs 2048 points
    python scripts/bench_register.py --pairs 10 --commands 3 --json
    python scripts/bench_register.py --compare '{"name": "robust", "options": {"rounds": 1}}'
    python scripts/bench_register.py --scans --repeats 2  # real scans, the command vs fpfh_ransac, per path
    python scripts/bench_register.py --scans --baseline ../other-checkout   # + that checkout's command, same run
    python scripts/bench_register.py --throughput rpm_ours_airplane --pairs 30   # solver vs network vs finished network
    python scripts/bench_register.py --throughput rpm_ours_airplane --pairs-of rpm_ours_human   # pairs it never saw

Pairs: :mod:`linereg.datasets.partial_vs_whole` on the ModelNet40 airplanes of the shared data (source a
hidden-point-removal view of 1024 points, target 2048 points of the whole shape). In one run,
first on the machine as it is ("quiet"), then again while this script keeps one extra
CPU-bound process spinning ("busy core"), it measures

* the solver (``robust``, :class:`~linereg.registration.robust.RobustRegistration`, the
  ``register`` default, numpy) per pair, after a warm-up pair;
* Open3D point-to-point ICP on the same pairs (the reference of the ratios);
* with ``--compare`` (a method config), another method on the same pairs: a ratio measured in the
  same run;
* the wall time of ``python -m train.register source=... target=...`` (start-up included), of
  ``python -c "import linereg.registration.api"`` (the library's start-up; the script fails if
  that import loads torch), and of ``python -c "import torch"`` (what a torch command pays first).

With ``--scans`` it times real scans of the shared data instead, on the machine as it is: the
3DMatch redkitchen fragments ``cloud_bin_4`` -> ``cloud_bin_0`` (about 300k points each), the
GeoTransformer demo pair ``src.npy`` -> ``ref.npy``, the FRICP statue scans (about 15k points; no
ground truth ships with them, so their errors are against the transform FRICP estimated) and
``--fragments`` room-fragment pairs of the shared 7-Scenes sequence (seed 0, as many from each
overlap bin of :data:`SPEED_BINS`: the ``fragments`` benchmark's three and 0.8-1 above them; each
fragment capped at ``--fragment-points`` random points, written as PLY).
Per pair, the median wall time of ``python -m train.register source=... target=...`` as a user
types it (the default method) and of the same command with ``method=fpfh_ransac`` (Open3D FPFH +
RANSAC + point-to-plane ICP: the reference), that of ``python -c "import torch"``, the errors of
both transforms (``result.json``) against the label, their ``confident`` flags, and the path the
default took: ``local`` (the first round's answer kept: not doubtful, or trusted by the dense
check) or ``global`` (the dense check doubted it; how many global candidates ran). A last table
gives each path's share of the pairs, its median and largest command time and its median ratio
to the reference.

With ``--throughput <network>`` (a pretrained name or run) it times :func:`linereg.register_many` in one
process on ``--pairs`` test pairs of that network's protocol (seed 0): the solver, the bare network
and the finished network (``refine=True``: as ``register_many`` runs it, the network dropped where its
path costs more than the solver's, and on every pair, ``keep_network=True``), as pairs per second with
their mean Err_R, confident share and, for the finished network, how often the solver ran;
``--pairs-of <network>`` takes the test pairs of that network's protocol instead (pairs the timed
network never trained on). The ways run in ``--repeats`` rounds (3), the order reversed every other
round; each ratio is the median over rounds of the round's ratio to the solver.

With ``--baseline <checkout>`` the same command of another checkout of linereg (another version)
is timed beside it, on the same pairs, in the same run, the two taking turns run by run (which of them
runs first alternates): ``command / baseline`` is the median over turns of the ratio of the turn's two
runs, the times beside it the medians of each.

Absolute times depend on the machine and on what else runs: compare the ratios of one run.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, NamedTuple

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from linereg.checks import nearest_rotation  # noqa: E402
from linereg.datasets.partial_vs_whole import partial_vs_whole_pairs  # noqa: E402
from linereg.io import write_point_cloud  # noqa: E402
from linereg.metrics import rotation_error_deg  # noqa: E402
from linereg.paths import shared_data_dir  # noqa: E402
from linereg.registration import METHODS  # noqa: E402
from linereg.registration.poses import rotation_gap_deg  # noqa: E402


def _spin() -> None:
    """A CPU-bound loop (the busy core)."""
    while True:
        pass


def _solver_times(method, pairs) -> tuple[list[float], list[float]]:
    """Seconds and Err_R (deg) of ``method`` on every pair after a warm-up on the first."""
    method(pairs[0].src_xyz, pairs[0].tgt_xyz)
    seconds, errors = [], []
    for pair in pairs[1:]:
        result = method(pair.src_xyz, pair.tgt_xyz)
        seconds.append(result.seconds)
        R_gt = torch.as_tensor(pair.gt_transform[:3, :3], dtype=torch.float64)
        errors.append(float(rotation_error_deg(torch.as_tensor(result.transform[:3, :3]), R_gt)))
    return seconds, errors


def _env(root: Path = ROOT) -> dict[str, str]:
    """The environment of the timed commands: the checkout ``root`` first on ``PYTHONPATH``."""
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")]))


def _turn(items: tuple, run: int) -> list[tuple[int, Any]]:
    """``(number, item)`` of each of ``items`` (checkouts, ways) in the order of run ``run``: as given on
    even runs, reversed on odd ones (none always runs first, right after another)."""
    numbered = list(enumerate(items))
    return numbered if run % 2 == 0 else numbered[::-1]


def paired_ratio(times: list[float], reference: list[float]) -> float:
    """The median over runs of ``times[i] / reference[i]``, two commands timed in the same turn: a slow
    spell of the machine falls on both of a turn's runs and cancels."""
    return statistics.median(spent / base for spent, base in zip(times, reference, strict=True))


def _wall(command: list[str], cwd: Path, repeats: int, roots: tuple[Path, ...] = (ROOT,)) -> list[list[float]]:
    """Wall-clock seconds of every run of ``command`` (must succeed) with each checkout of ``roots``'
    code, the checkouts taking turns run by run (:func:`_turn`)."""
    times = [[] for _ in roots]
    for run in range(repeats):
        for number, root in _turn(roots, run):
            start = time.perf_counter()
            subprocess.run(command, cwd=cwd, env=_env(root), check=True, capture_output=True)
            times[number].append(time.perf_counter() - start)
    return times


_TORCH_FREE = "import sys, linereg.registration.api; assert 'torch' not in sys.modules, 'torch was imported'"


def measure(pairs, folder: Path, commands: int, compare: dict | None, baseline: Path | None = None) -> dict[str, float]:
    """One row: solver, ICP, compared method and command times (medians) and their ratios; with
    ``baseline``, that checkout's command too."""
    robust, robust_err = _solver_times(METHODS.build({"name": "robust"}), pairs)
    icp, icp_err = _solver_times(METHODS.build({"name": "icp_point"}), pairs)
    register = [sys.executable, "-m", "train.register", "source=src.ply", "target=tgt.ply"]
    roots = (ROOT,) if baseline is None else (ROOT, baseline)
    command_runs, *before = _wall(register, folder, commands, roots)
    command = statistics.median(command_runs)
    library, floor = (
        statistics.median(*_wall([sys.executable, "-c", code], folder, commands))
        for code in (_TORCH_FREE, "import torch")
    )
    row = {
        "solver_s": statistics.median(robust),
        "solver_max_s": max(robust),
        "solver_err_r_deg_median": float(np.median(robust_err)),
        "icp_s": statistics.median(icp),
        "icp_err_r_deg_median": float(np.median(icp_err)),
        "command_s": command,
        "import_api_s": library,
        "import_torch_s": floor,
    }
    row["solver_vs_icp"] = row["solver_s"] / row["icp_s"]
    row["command_vs_import_torch"] = command / floor
    if baseline is not None:
        row["baseline_command_s"] = statistics.median(before[0])
        row["command_vs_baseline"] = paired_ratio(command_runs, before[0])
    if compare is not None:
        other, other_err = _solver_times(METHODS.build(compare), pairs)
        row["compared_s"] = statistics.median(other)
        row["compared_err_r_deg_median"] = float(np.median(other_err))
        row["compared_vs_icp"] = row["compared_s"] / row["icp_s"]
    return row


# name: (source, target, label), relative to the shared data; the label is a transform file or the
# block (target i, source j) of a 3DMatch gt.log. The statue pair ships no ground truth: its label is
# the transform FRICP estimated (scans/fricp_statue/SOURCE.md).
SCAN_PAIRS = {
    "redkitchen 4->0": (
        "3dmatch/redkitchen_0_4/cloud_bin_4.ply",
        "3dmatch/redkitchen_0_4/cloud_bin_0.ply",
        ("3dmatch/geotransformer_demo/benchmarks/3DMatch/7-scenes-redkitchen/gt.log", 0, 4),
    ),
    "geotransformer demo": (
        "3dmatch/geotransformer_demo/demo/src.npy",
        "3dmatch/geotransformer_demo/demo/ref.npy",
        "3dmatch/geotransformer_demo/demo/gt.npy",
    ),
    "statue (FRICP's estimate)": (
        "scans/fricp_statue/source.ply",
        "scans/fricp_statue/target.ply",
        "scans/fricp_statue/m3trans.txt",
    ),
}


class ScanPair(NamedTuple):
    """A scan pair as files, and its label (``(4, 4)``, exactly rigid)."""

    name: str
    source: Path
    target: Path
    truth: np.ndarray


def _register_runs(
    arguments: list[str], folder: Path, repeats: int, roots: tuple[Path, ...] = (ROOT,)
) -> list[tuple[list[float], dict]]:
    """Per checkout of ``roots``, taking turns run by run (:func:`_turn`): the wall-clock seconds of
    every run of ``python -m train.register <arguments>`` with its code, and its last ``result.json``."""
    folder.mkdir()
    times, reports = [[] for _ in roots], [None for _ in roots]
    for run in range(repeats):
        for number, root in _turn(roots, run):
            out = folder / f"checkout{number}" / f"run{run}"
            command = [sys.executable, "-m", "train.register", *arguments, f"hydra.run.dir={out}"]
            start = time.perf_counter()
            done = subprocess.run(command, cwd=folder, env=_env(root), capture_output=True, text=True)
            times[number].append(time.perf_counter() - start)
            if done.returncode != 0:
                lines = (done.stderr or done.stdout).strip().splitlines() or ["no output"]
                raise SystemExit(f"{' '.join(command[1:])} failed: {lines[-1]}")
            reports[number] = json.loads((out / "result.json").read_text())
    return list(zip(times, reports, strict=True))


def pose_errors(transform, truth: np.ndarray) -> tuple[float, float]:
    """Rotation error (deg) and translation error (input units) of ``transform`` against ``truth (4, 4)``."""
    transform = np.asarray(transform, dtype=np.float64)
    rotation = float(rotation_gap_deg(transform[None, :3, :3], truth[:3, :3])[0])
    return rotation, float(np.linalg.norm(transform[:3, 3] - truth[:3, 3]))


def _rigid(transform) -> np.ndarray:
    """``transform`` as float64 with the nearest rotation (stored ones are float32)."""
    truth = np.array(transform, dtype=np.float64)
    truth[:3, :3] = nearest_rotation(truth[:3, :3])
    return truth


def _label(data: Path, label: str | tuple[str, int, int]) -> np.ndarray:
    """The label of a :data:`SCAN_PAIRS` entry."""
    from linereg.datasets.formats import read_log
    from linereg.io import read_transform

    if isinstance(label, str):
        return _rigid(read_transform(data / label))
    log, target, source = label
    return _rigid(next(entry.transform for entry in read_log(data / log) if (entry.i, entry.j) == (target, source)))


SEQUENCE = "rgbd/7scenes_first_half/data"
"""The posed RGB-D sequence of the room fragments, relative to the shared data."""
SPEED_BINS = ((0.2, 0.3), (0.3, 0.5), (0.5, 0.8), (0.8, 1.0))
"""Overlap bins of the room-fragment pairs timed with ``--scans``: the ``fragments`` benchmark's
three and the pairs above them, whose first-round answers are mostly right."""


def scan_pairs(data: Path, folder: Path, fragments: int, points: int) -> list[ScanPair]:
    """The pairs of :data:`SCAN_PAIRS` found under ``data`` (absent ones skipped with a note on
    stderr), then ``fragments`` room-fragment pairs of the shared sequence (seed 0, as many from
    each bin of :data:`SPEED_BINS`), each cloud capped at ``points`` random points and written as
    PLY into ``folder``."""
    from linereg.datasets.benchmark_pairs import select_pairs

    found = []
    for name, (source, target, label) in SCAN_PAIRS.items():
        label_file = label if isinstance(label, str) else label[0]
        missing = [path for path in (source, target, label_file) if not (data / path).is_file()]
        if missing:
            print(f"skipping {name}: {', '.join(str(data / path) for path in missing)} not found", file=sys.stderr)
            continue
        found.append(ScanPair(name, data / source, data / target, _label(data, label)))
    if fragments > 0 and not (data / SEQUENCE).is_dir():
        print(f"skipping the room fragments: {data / SEQUENCE} not found", file=sys.stderr)
    elif fragments > 0:
        bins = [list(b) for b in SPEED_BINS]
        sequence = {"name": "fragments", "root": str(data / SEQUENCE), "dense_points": points, "bins": bins}
        for index, pair in enumerate(select_pairs(sequence, pairs=fragments, seed=0)):
            source, target = folder / f"fragments{index}_src.ply", folder / f"fragments{index}_tgt.ply"
            write_point_cloud(source, pair.src_xyz)
            write_point_cloud(target, pair.tgt_xyz)
            overlap = pair.meta["overlap"]
            found.append(ScanPair(f"fragments {index} ({overlap:.2f})", source, target, _rigid(pair.gt_transform)))
    return found


def measure_scans(pairs: list[ScanPair], folder: Path, repeats: int, baseline: Path | None = None) -> dict[str, dict]:
    """One row per pair: the command's and the reference's times, their ratio, both methods'
    errors and ``confident`` flags, and the command's path (``local``: the first round's answer
    kept; ``global``: global candidates ran, ``global_candidates`` of them); with ``baseline``, that
    checkout's command time, ratio and flag."""
    rows = {}
    for number, pair in enumerate(pairs):
        place = folder / f"pair{number}"
        place.mkdir()
        arguments = [f"source={pair.source}", f"target={pair.target}"]
        roots = (ROOT,) if baseline is None else (ROOT, baseline)
        (command_runs, report), *before = _register_runs(arguments, place / "default", repeats, roots)
        ((reference_runs, ref_report),) = _register_runs(
            [*arguments, "method=fpfh_ransac"], place / "fpfh_ransac", repeats
        )
        command, reference = statistics.median(command_runs), statistics.median(reference_runs)
        floor = statistics.median(*_wall([sys.executable, "-c", "import torch"], place, repeats))
        (err_r, err_t), (ref_r, ref_t) = (pose_errors(r["transform"], pair.truth) for r in (report, ref_report))
        tried = report["solver"]["global_candidates"]
        rows[pair.name] = {
            "source_points": report["source_points"],
            "target_points": report["target_points"],
            "path": "global" if tried else "local",
            "global_candidates": tried,
            "command_s": command,
            "fpfh_ransac_command_s": reference,
            "command_vs_fpfh_ransac": command / reference,
            "import_torch_s": floor,
            "command_vs_import_torch": command / floor,
            "err_r_deg": err_r,
            "translation_error": err_t,
            "confident": report["confident"],
            "fpfh_ransac_err_r_deg": ref_r,
            "fpfh_ransac_translation_error": ref_t,
            "fpfh_ransac_confident": ref_report["confident"],
        }
        if before:
            ((before_runs, before_report),) = before
            rows[pair.name].update(
                baseline_command_s=statistics.median(before_runs),
                command_vs_baseline=paired_ratio(command_runs, before_runs),
                baseline_err_r_deg=pose_errors(before_report["transform"], pair.truth)[0],
                baseline_confident=before_report["confident"],
            )
        print(f"{pair.name}: {rows[pair.name]}", file=sys.stderr, flush=True)
    return rows


def throughput(network: str, count: int, pairs_of: str | None = None, rounds: int = 3) -> dict[str, dict[str, float]]:
    """``register_many`` on ``count`` test pairs of ``network``'s protocol (of ``pairs_of``'s: pairs
    the network never trained on), in one process, ``rounds`` times (the ways' order reversed every
    other round): per way (``solver``, ``network``, ``finished network`` with and without
    ``keep_network``), pairs per second (the median round), its ratio to the solver's (the median over
    rounds of the round's ratio), and from the first round the mean and max Err_R, the confident share,
    its precision (confident answers within 5 degrees) and how often the solver ran."""
    from linereg import pretrained, register_many
    from linereg.datasets.benchmark_pairs import run_pairs

    owner = pairs_of or network
    run = str(pretrained.path(owner)) if pretrained.is_name(owner) else owner
    pairs = run_pairs(run=run, split="test", pairs=count, seed=0)
    clouds = [(pair.src_xyz.astype(np.float64), pair.tgt_xyz.astype(np.float64)) for pair in pairs]
    finished = {"method": network, "refine": True}
    ways = {
        "solver": {},
        "network": {"method": network},
        "finished network, every pair": {**finished, "keep_network": True},
        "finished network": finished,
    }
    for options in ways.values():
        list(register_many(clouds[:1], progress=False, **options))  # warm-up: imports, the model loaded
    rows, seconds = {}, {way: [] for way in ways}
    for round_ in range(rounds):
        for _, way in _turn(tuple(ways), round_):
            start = time.perf_counter()
            results = list(register_many(clouds, progress=False, **ways[way]))
            seconds[way].append(time.perf_counter() - start)
            rows.setdefault(way, _throughput_row(way, results, pairs))
    for way in ways:
        rows[way]["pairs_per_s"] = len(pairs) / statistics.median(seconds[way])
        rows[way]["vs_solver"] = paired_ratio(seconds["solver"], seconds[way])
    return {way: rows[way] for way in ways}


def _throughput_row(way: str, results: list, pairs: list) -> dict[str, float]:
    """Err_R, the confident share, its precision and how often the solver ran, of one way's ``results``."""
    errors = np.array([_rotation_error(r.transformation, p.gt_transform) for r, p in zip(results, pairs, strict=True)])
    confident = np.array([r.confident for r in results])
    return {
        "err_r_deg_mean": float(errors.mean()),
        "err_r_deg_max": float(errors.max()),
        "confident_share": float(confident.mean()),
        "confident_precision": float((confident & (errors <= 5.0)).sum() / max(confident.sum(), 1)),
        "solver_ran_share": float(np.mean([r.info.get("solver_ran", way == "solver") for r in results])),
    }


def _rotation_error(transform: np.ndarray, truth: np.ndarray) -> float:
    return float(rotation_gap_deg(transform[None, :3, :3], _rigid(truth)[:3, :3])[0])


def print_throughput(network: str, rows: dict[str, dict[str, float]], pairs_of: str | None = None) -> None:
    """The ``--throughput`` table, ratios against the solver."""
    pairs = f"the test pairs of {pairs_of}'s protocol" if pairs_of else "its protocol's test pairs"
    print(f"{network}: {pairs}, one process, {os.cpu_count()} CPUs\n")
    print("| way | pairs / s | vs the solver | Err_R mean (max), deg | confident | precision | solver ran |")
    print("|---|---:|---:|---|---:|---:|---:|")
    for way, row in rows.items():
        precision = f"{row['confident_precision']:.2f}" if row["confident_share"] else "-"
        print(
            f"| {way} | {row['pairs_per_s']:.2f} | {row['vs_solver']:.2f}x "
            f"| {row['err_r_deg_mean']:.2f} ({row['err_r_deg_max']:.1f}) | {row['confident_share']:.2f} "
            f"| {precision} | {row['solver_ran_share']:.2f} |"
        )


def path_summary(rows: dict[str, dict]) -> dict[str, dict]:
    """Per path (``local``, ``global``): pairs, their share, the command's median and largest wall
    time and the median ratio to the reference command."""
    summary = {}
    for path in ("local", "global"):
        chosen = [row for row in rows.values() if row["path"] == path]
        if chosen:
            summary[path] = {
                "pairs": len(chosen),
                "share": len(chosen) / len(rows),
                "command_s_median": statistics.median(row["command_s"] for row in chosen),
                "command_s_max": max(row["command_s"] for row in chosen),
                "command_vs_fpfh_ransac_median": statistics.median(row["command_vs_fpfh_ransac"] for row in chosen),
            }
    return summary


def print_scans(rows: dict[str, dict], repeats: int) -> None:
    """The ``--scans`` rows as markdown tables: per pair, then per path."""
    print(f"real scans, medians of {repeats} run(s) of each command, {os.cpu_count()} CPUs\n")
    print(
        "| pair | points (source/target) | path | command wall (s) | fpfh_ransac command wall (s) "
        "| command / fpfh_ransac | command / import torch | Err_R (deg), translation, confident "
        "| fpfh_ransac Err_R (deg), translation, confident |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name, row in rows.items():
        path = row["path"] if row["path"] == "local" else f"global ({row['global_candidates']})"
        print(
            f"| {name} | {row['source_points']}/{row['target_points']} | {path} | {row['command_s']:.2f} "
            f"| {row['fpfh_ransac_command_s']:.2f} | {row['command_vs_fpfh_ransac']:.2f}x "
            f"| {row['command_vs_import_torch']:.2f}x "
            f"| {row['err_r_deg']:.2f}, {row['translation_error']:.4f}, {row['confident']} "
            f"| {row['fpfh_ransac_err_r_deg']:.2f}, {row['fpfh_ransac_translation_error']:.4f}, "
            f"{row['fpfh_ransac_confident']} |"
        )
    print("\n| path | pairs | share | command wall median (s) | max (s) | command / fpfh_ransac (median) |")
    print("|---|---|---|---|---|---|")
    for path, row in path_summary(rows).items():
        print(
            f"| {path} | {row['pairs']} | {row['share']:.0%} | {row['command_s_median']:.2f} "
            f"| {row['command_s_max']:.2f} | {row['command_vs_fpfh_ransac_median']:.2f}x |"
        )
    if all("command_vs_baseline" in row for row in rows.values()):
        ratios = [row["command_vs_baseline"] for row in rows.values()]
        flips = [name for name, row in rows.items() if row["confident"] != row["baseline_confident"]]
        print(
            f"\ncommand / baseline command: median {statistics.median(ratios):.2f}x, largest {max(ratios):.2f}x; "
            f"confident changed on: {', '.join(flips) or 'none'}"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=5, help="timed pairs (one more is the warm-up)")
    parser.add_argument("--commands", type=int, default=3, help="runs of each command")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--compare", type=json.loads, help='method config (JSON) to time beside, e.g. {"name": "fgr"}')
    parser.add_argument("--scans", action="store_true", help="time real room scans: the command vs fpfh_ransac")
    parser.add_argument("--repeats", type=int, help="--scans: runs of each command (2); --throughput: rounds (3)")
    parser.add_argument("--fragments", type=int, default=16, help="room-fragment pairs with --scans (4 bins)")
    parser.add_argument("--fragment-points", type=int, default=100_000, help="points of each fragment with --scans")
    parser.add_argument("--baseline", type=Path, help="another checkout of linereg whose command is timed beside")
    parser.add_argument("--throughput", metavar="NETWORK", help="pairs per second of solver, network, finished network")
    parser.add_argument("--pairs-of", metavar="NETWORK", help="with --throughput: that network's protocol's test pairs")
    args = parser.parse_args(argv)
    if args.pairs_of is not None and args.throughput is None:
        parser.error("--pairs-of needs --throughput")
    if args.throughput is not None:
        rows = throughput(args.throughput, args.pairs, args.pairs_of, args.repeats or 3)
        print_throughput(args.throughput, rows, args.pairs_of)
        return 0
    if args.baseline is not None and not (args.baseline / "train" / "register.py").is_file():
        parser.error(f"--baseline {args.baseline}: not a checkout of linereg (no train/register.py)")
    if args.compare is not None:
        METHODS.build(args.compare)  # a bad config fails here, before any timing
    data = shared_data_dir()
    if data is None:
        parser.error("the shared data folder was not found (set $LINEREG_SHARED_DATA)")
    if args.scans:
        with tempfile.TemporaryDirectory() as folder:
            pairs = scan_pairs(data, Path(folder), args.fragments, args.fragment_points)
            rows = measure_scans(pairs, Path(folder), args.repeats or 2, args.baseline)
        if not rows:
            parser.error(f"no scan pair was found under {data}")
        if args.json:
            print(json.dumps({"pairs": rows, "paths": path_summary(rows)}))
        else:
            print_scans(rows, args.repeats or 2)
        return 0
    pairs = partial_vs_whole_pairs(
        data / "modelnet40_normal_resampled", pairs=args.pairs + 1, seed=0, patterns=["airplane/*.txt"]
    )
    rows = {}
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        write_point_cloud(folder / "src.ply", pairs[1].src_xyz)
        write_point_cloud(folder / "tgt.ply", pairs[1].tgt_xyz)
        rows["quiet"] = measure(pairs, folder, args.commands, args.compare, args.baseline)
        spinner = multiprocessing.Process(target=_spin, daemon=True)
        spinner.start()
        try:
            rows["busy core"] = measure(pairs, folder, args.commands, args.compare, args.baseline)
        finally:
            spinner.terminate()
            spinner.join()
    for key in ("solver_s", "command_s"):
        rows["busy core"][f"{key}_busy_vs_quiet"] = rows["busy core"][key] / rows["quiet"][key]
    if args.json:
        print(json.dumps(rows))
        return 0
    print(f"{args.pairs} partial-vs-whole airplane pairs (1024 vs 2048 points), {os.cpu_count()} CPUs\n")
    print(
        "| machine | solver median (s) | max (s) | median Err_R (deg) | ICP (s) | solver time / ICP time "
        "| command wall (s) | import api (s) | import torch (s) | command / import torch |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, row in rows.items():
        print(
            f"| {name} | {row['solver_s']:.2f} | {row['solver_max_s']:.2f} | {row['solver_err_r_deg_median']:.3f} "
            f"| {row['icp_s']:.3f} | {row['solver_vs_icp']:.0f}x | {row['command_s']:.2f} "
            f"| {row['import_api_s']:.2f} | {row['import_torch_s']:.2f} | {row['command_vs_import_torch']:.2f}x |"
        )
    if args.compare is not None:
        print(f"\ncompared method ({json.dumps(args.compare)}), same pairs:\n")
        print("| machine | compared median (s) | median Err_R (deg) | compared / ICP | solver / compared |")
        print("|---|---|---|---|---|")
        for name, row in rows.items():
            print(
                f"| {name} | {row['compared_s']:.2f} | {row['compared_err_r_deg_median']:.3f} "
                f"| {row['compared_vs_icp']:.0f}x | {row['solver_s'] / row['compared_s']:.2f}x |"
            )
    if args.baseline is not None:
        print(f"\ncommand / the command of {args.baseline}, same pairs:")
        for name, row in rows.items():
            times = f"{row['command_s']:.2f} s / {row['baseline_command_s']:.2f} s"
            print(f"- {name}: {times} = {row['command_vs_baseline']:.2f}x")
    busy = rows["busy core"]
    print(
        f"\nbusy core / quiet: solver {busy['solver_s_busy_vs_quiet']:.2f}x, "
        f"command {busy['command_s_busy_vs_quiet']:.2f}x"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
