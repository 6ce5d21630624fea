"""Score networks beyond their own test split: each protocol's generalization splits, one table each.

    python scripts/score_generalization.py --out outputs/generalization            # the shipped networks
    python scripts/score_generalization.py --out <dir> --models rpm_ours_airplane=<run> --register

For every protocol, the networks trained on it (by default the shipped ``rpm_{gt,cd,ours}_<protocol>``
of :mod:`linereg.pretrained`) are scored by ``linereg-evaluate`` on its test pairs (``in-protocol``)
and on every generalization split of :data:`SPLITS` (a dataset config of ``configs/dataset/``), with
the identity's error on the same pairs and, with ``--register``, that of ``linereg.register`` (the
default solver, no network; once per protocol and split). Each score is cached in
``<out>/<model>/<split>.json``, so a cut run resumes; ``<out>/table.md`` holds mean Err_R (degrees) per protocol.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir

from linereg.train import CONFIG_DIR
from linereg.train.evaluate import evaluate

IN_PROTOCOL = "in-protocol"
# protocol -> (column, dataset config or None for the checkpoint's own test pairs)
SPLITS: dict[str, list[tuple[str, str | None]]] = {
    "airplane": [
        (IN_PROTOCOL, None),
        ("view vs whole shape", "airplane_view_vs_whole"),
        ("7 other ModelNet40 classes", "airplane_other_categories"),
    ],
    "human": [(IN_PROTOCOL, None), ("view vs view", "human_view_vs_view")],
    "real": [(IN_PROTOCOL, None), ("Kinect frames (SLAM poses)", "kinect_frames")],
}
LOSSES = ("gt", "cd", "ours")


def score(checkpoint: str, dataset: str | None, *, register: Path | None) -> dict[str, float]:
    """Mean Err_R of ``checkpoint`` and of the identity on the test split of ``dataset`` (``None``:
    the checkpoint's own); with ``register`` (a cache file shared by the networks scored on the same
    pairs), also that of ``linereg.register``."""
    overrides = [f"checkpoint={checkpoint}", "progress=false", "num_figures=0", "with_loss=false"]
    overrides += [f"dataset={dataset}"] if dataset else []
    with tempfile.TemporaryDirectory() as scratch, initialize_config_dir(CONFIG_DIR, version_base="1.3"):
        cfg = compose("evaluate", overrides=[*overrides, f"output_dir={scratch}", f"paths.root_dir={Path.cwd()}"])
        metrics = evaluate(cfg)
    result = {
        "pairs": metrics["num_pairs"],
        "model": metrics["model"]["err_r_deg_mean"],
        "identity": metrics["identity"]["err_r_deg_mean"],
        "confident": metrics["model"].get("confident_share"),
    }
    if register is not None:
        if not register.is_file():
            register.parent.mkdir(parents=True, exist_ok=True)
            register.write_text(json.dumps({"err_r_deg_mean": register_error(cfg)}))
        result["register"] = json.loads(register.read_text())["err_r_deg_mean"]
    return result


def register_error(cfg) -> float:
    """Mean Err_R (degrees) of ``linereg.register`` (the default solver) on the pairs ``cfg`` evaluated
    (:func:`score` ran :func:`evaluate` on it, which fills in ``trainer.num_points``)."""
    import torch

    import linereg
    from linereg.checkpoint import load_checkpoint
    from linereg.datasets.splits import build_split
    from linereg.metrics import registration_errors
    from linereg.registry import plain

    dataset_config = plain(cfg.dataset) if cfg.get("dataset") else load_checkpoint(cfg.checkpoint)["config"]["dataset"]
    dataset = build_split(dataset_config, cfg.split, progress=False)
    errors = []
    for index in range(len(dataset)):
        pair = dataset[index]
        src, tgt = (np.asarray(cloud, dtype=np.float64) for cloud in (pair.src_xyz, pair.tgt_xyz))
        estimate = torch.from_numpy(linereg.register(src, tgt).transformation)[None]
        truth = torch.as_tensor(np.asarray(pair.gt_transform, dtype=np.float64))[None]
        errors.append(float(registration_errors(estimate, truth, torch.from_numpy(src)[None])["err_r_deg"][0]))
    return float(np.mean(errors))


def table(results: Mapping[str, Mapping[str, Mapping[str, float]]]) -> str:
    """Markdown: per protocol, a row per network, identity and register, a column per split."""
    lines = []
    for protocol, splits in SPLITS.items():
        columns = [column for column, _ in splits]
        lines += [f"### {protocol}", "", "| network | " + " | ".join(columns) + " |"]
        lines.append("|---|" + "---:|" * len(columns))
        names = [f"rpm_{loss}_{protocol}" for loss in LOSSES if f"rpm_{loss}_{protocol}" in results]
        for name in names:
            cells = [results[name].get(column, {}).get("model") for column in columns]
            lines.append(f"| `{name}` | " + " | ".join("" if v is None else f"{v:.2f}" for v in cells) + " |")
        scored = [results[name] for name in names]
        for row in ("identity", "register"):
            cells = [next((r[c][row] for r in scored if row in r.get(c, {})), None) for c in columns]
            if any(value is not None for value in cells):
                label = "identity (no motion)" if row == "identity" else "`linereg.register`"
                lines.append(f"| {label} | " + " | ".join("" if v is None else f"{v:.2f}" for v in cells) + " |")
        counts = [next((r[c]["pairs"] for r in scored if c in r), "") for c in columns]
        lines += ["", "Pairs: " + ", ".join(f"{c} {n}" for c, n in zip(columns, counts, strict=True)), ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="folder of the cached scores and table.md")
    parser.add_argument("--models", nargs="*", default=[], help="name=checkpoint pairs (default: the shipped ones)")
    parser.add_argument("--register", action="store_true", help="also score linereg.register on the same pairs")
    args = parser.parse_args(argv)
    models = dict(item.split("=", 1) for item in args.models) or {
        f"rpm_{loss}_{protocol}": f"rpm_{loss}_{protocol}" for protocol in SPLITS for loss in LOSSES
    }
    results: dict[str, dict[str, dict[str, float]]] = {}
    for name, checkpoint in models.items():
        protocol = name.rsplit("_", 1)[-1]
        for column, dataset in SPLITS.get(protocol, []):
            cached = args.out / name / f"{dataset or 'test'}.json"
            if not cached.is_file():
                start = time.perf_counter()
                shared = args.out / "register" / f"{protocol}_{dataset or 'test'}.json" if args.register else None
                value = score(checkpoint, dataset, register=shared)
                cached.parent.mkdir(parents=True, exist_ok=True)
                cached.write_text(json.dumps(value, indent=2))
                print(f"{name} on {column}: {value['model']:.2f} deg ({time.perf_counter() - start:.0f} s)", flush=True)
            results.setdefault(name, {})[column] = json.loads(cached.read_text())
    (args.out / "table.md").write_text(table(results))
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
