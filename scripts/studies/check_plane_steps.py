"""Which final steps remove the sampling offset of independent samplings.

    python scripts/studies/check_plane_steps.py human --pairs 40
    python scripts/studies/check_plane_steps.py dragon --pairs 2 --epsilon 0.001 0.01 0.1 --neighbours 10 20

For every pair of a benchmark source (``configs/benchmark/<source>.yaml``) it runs the ``register``
default without its last steps (``plane_steps: 0``: the point-to-point pose after the fine
polish), then refines that pose with ``--steps`` Gauss-Newton steps of each variant of
:func:`linereg.registration.planes.plane_to_plane_irls` at the default's Welsch scale (``plane_nu``
target point spacings):

* ``point-to-plane``: no source covariance and a flat target disc (thickness 1e-6), the
  point-to-plane limit of the same objective (target normals from ``k`` neighbours);
* ``plane-to-plane k=<k> eps=<e>``: both clouds' :func:`surface_covariances`, every ``k`` of
  ``--neighbours`` and ``e`` of ``--epsilon`` (the default: k = 10, eps = 0.01).

It prints, per variant, the mean and largest Err_R (degrees) and the mean Err_pw (l2, x10^-1, the
benchmark's units) over the pairs, the point-to-point pose first.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from linereg.datasets.benchmark_pairs import select_pairs
from linereg.knn import NearestNeighbors
from linereg.metrics import registration_errors
from linereg.registration.evaluation import point_spacing
from linereg.registration.methods import METHODS
from linereg.registration.planes import plane_to_plane_irls, surface_covariances
from linereg.registration.poses import as_matrices
from linereg.registration.robust_options import PlaneOptions


def errors(transform: np.ndarray, truth: np.ndarray, src: np.ndarray) -> tuple[float, float]:
    """Err_R (degrees) and Err_pw l2 of one pair, as the benchmark scores it (:func:`registration_errors`)."""
    values = registration_errors(
        torch.from_numpy(transform)[None], torch.from_numpy(truth)[None], torch.from_numpy(src)[None]
    )
    return float(values["err_r_deg"][0]), float(values["err_pw_l2"][0])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", help="benchmark source: human, dragon, airplane, pvw_human, ...")
    parser.add_argument("--pairs", type=int, default=40)
    parser.add_argument("--steps", type=int, default=PlaneOptions.steps)
    parser.add_argument("--neighbours", type=int, nargs="+", default=[6, 10, 15, 20])
    parser.add_argument("--epsilon", type=float, nargs="+", default=[0.001, 0.01, 0.03, 0.1])
    args = parser.parse_args(argv)
    default = PlaneOptions()
    solver = METHODS.build({"name": "robust", "num_points": 2048, "options": {"plane_steps": 0}})
    variants = [("point-to-plane k=10", None, 10, 1e-6)]
    variants += [(f"plane-to-plane k={k} eps={e:g}", k, k, e) for k in args.neighbours for e in args.epsilon]
    scores: dict[str, list[tuple[float, float]]] = {"point-to-point (no steps)": []}
    scores.update({name: [] for name, *_ in variants})
    for pair in select_pairs({"name": args.source}, pairs=args.pairs, seed=0):
        src, tgt = pair.src_xyz.astype(np.float64), pair.tgt_xyz.astype(np.float64)
        truth = np.asarray(pair.gt_transform, dtype=np.float64)
        start = solver(src, tgt).transform
        scores["point-to-point (no steps)"].append(errors(start, truth, src))
        tree = NearestNeighbors(tgt)
        nu = default.nu * point_spacing(tgt, tree)
        for name, src_k, tgt_k, epsilon in variants:
            src_cov = np.zeros((len(src), 3, 3)) if src_k is None else surface_covariances(src, src_k, epsilon)
            poses = plane_to_plane_irls(
                (start[None, :3, :3], start[None, :3, 3]),
                src,
                src_cov,
                tree,
                surface_covariances(tgt, tgt_k, epsilon),
                nu,
                args.steps,
            )
            scores[name].append(errors(as_matrices(poses)[0], truth, src))
    count = len(scores["point-to-point (no steps)"])
    print(f"{args.source}, {count} pairs, {args.steps} steps at {default.nu} spacings")
    print(f"{'final steps':36s} {'Err_R mean':>10s} {'max':>7s} {'Err_pw l2 (x10^-1)':>19s}")
    for name, values in scores.items():
        err_r, err_pw = np.array(values).T
        print(f"{name:36s} {err_r.mean():10.4f} {err_r.max():7.3f} {10 * err_pw.mean():19.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
