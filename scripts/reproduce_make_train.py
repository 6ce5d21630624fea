"""The `make train` figures of the README: the embedded default, timed, from an empty pair cache.

    python scripts/reproduce_make_train.py                      # seed 0, into outputs/make_train/s0
    python scripts/reproduce_make_train.py --seed 1 --out /tmp/mt
    python scripts/reproduce_make_train.py loss.variant=authors     # + overrides of both steps

Two timed steps, each in a child process with one thread: generating the default's pairs (the
easy variant of the training split, validation and test) into an empty cache, then
``python -m train seed=<seed> trainer.threads=1`` on that cache. Prints the CPU seconds (user +
sys, children included) of each step and their sum, the wall time, the test Err_R of the last
checkpoint and the validation curve. With one thread, user + sys approximates the wall time on
one quiet core; the default itself (``trainer.threads=null``) uses every core.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def generate(cache_dir: str, overrides: list[str]) -> None:
    """Build the run's training (its curriculum's variants), validation and test pairs into ``cache_dir``."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from linereg.datasets.splits import build_split
    from linereg.train import CONFIG_DIR

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(
            "train",
            overrides=[f"paths.root_dir={ROOT}", "paths.output_dir=unused", f"paths.cache_dir={cache_dir}", *overrides],
        )
    config = OmegaConf.to_container(cfg, resolve=True)
    variants = {stage["variant"] for stage in config["curriculum"]["stages"].values()}
    for variant in sorted(variants, key=str):
        build_split(config["dataset"], "train", variant=variant, subset=None, seed=0, progress=False)
    for split in ("val", "test"):
        build_split(config["dataset"], split, subset=None, seed=0, progress=False)


def timed(command: list[str], log: Path) -> tuple[float, float]:
    """Run ``command`` (output into ``log``); its CPU seconds (user + sys) and wall seconds."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    with log.open("w") as out:
        subprocess.run(command, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, check=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return cpu, time.perf_counter() - start


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "make_train")
    parser.add_argument("--generate", metavar="CACHE_DIR", help=argparse.SUPPRESS)  # the first step's child
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of the default (key=value)")
    args = parser.parse_args(argv)
    if args.generate:
        generate(args.generate, args.overrides)
        return
    run = args.out.resolve() / f"s{args.seed}"
    if run.exists():
        parser.error(f"{run} exists: remove it to rerun")
    run.mkdir(parents=True)
    cache = run / "pair_cache"
    os.environ.update(OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    generation = timed([sys.executable, __file__, "--generate", str(cache), *args.overrides], run / "generate.log")
    training = timed(
        [
            sys.executable,
            "-m",
            "train",
            f"seed={args.seed}",
            "trainer.threads=1",
            "trainer.progress=false",
            f"paths.cache_dir={cache}",
            f"hydra.run.dir={run}",
            *args.overrides,
        ],
        run / "train.out",
    )
    metrics = json.loads((run / "metrics.json").read_text())["metrics"]
    records = map(json.loads, (run / "scalars.jsonl").read_text().splitlines())
    curve = [record["val/err_r_deg_mean"] for record in records if "val/err_r_deg_mean" in record]
    print(
        f"CPU s (user + sys, one thread): generating the pairs {generation[0]:.0f}, training and evaluating "
        f"{training[0]:.0f}, total {generation[0] + training[0]:.0f}; wall {generation[1] + training[1]:.0f} s"
    )
    print(
        f"test Err_R mean {metrics['test/err_r_deg_mean']:.2f}, median {metrics['test/err_r_deg_median']:.2f} deg "
        f"(identity {metrics['test/identity/err_r_deg_mean']:.2f})"
    )
    print("validation Err_R mean per epoch (first: before training):", ", ".join(f"{v:.2f}" for v in curve))


if __name__ == "__main__":
    main()
