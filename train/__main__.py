"""``python -m train [experiment=...] [key=value ...]``: a thin Hydra wrapper around
:func:`linereg.train.loop.train` (``configs/train.yaml``). Returns the optimised metric to sweepers."""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from linereg.train import distributed
from linereg.train.loop import train


@hydra.main(version_base="1.3", config_path="../configs", config_name="train")
def main(cfg: DictConfig) -> float | None:
    metrics = train(cfg)["metrics"]
    value = metrics.get(cfg.optimized_metric)
    return None if value is None else float(value)


if __name__ == "__main__":
    sys.argv.extend(distributed.hydra_rank_overrides())
    main()
