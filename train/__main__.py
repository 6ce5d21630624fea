"""``linereg-train [experiment=...] [key=value ...]`` (or ``python -m train`` in a checkout): a thin
Hydra wrapper around :func:`linereg.train.loop.train` (``configs/train.yaml``; ``linereg-train --help``).
Returns the optimised metric to sweepers."""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from linereg.train import CONFIG_DIR, distributed
from linereg.train.cli import reported, run_app

COMMAND = "linereg-train"


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="train")
def _train(cfg: DictConfig) -> float | None:
    with reported(COMMAND):
        # Imported here: a missing [train] extra (matplotlib, tensorboard) is named, not a traceback.
        from linereg.train.loop import train

        metrics = train(cfg)["metrics"]
    value = metrics.get(cfg.optimized_metric)
    return None if value is None else float(value)


def main() -> float | None:
    """The command: Hydra parses ``sys.argv`` (plus the rank overrides of a distributed launch)."""
    sys.argv.extend(distributed.hydra_rank_overrides())
    return run_app(COMMAND, _train)


if __name__ == "__main__":
    main()
