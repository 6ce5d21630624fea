"""Register one pair of point clouds: ``python -m train.register source=a.ply target=b.ply``.

Hydra overrides select everything else (``configs/register/register.yaml``; the app has its own
config root so that ``loss=...`` names a loss, not the training configs' ``loss`` group)::

    python -m train.register source=a.ply target=b.ply                      # linereg default
    python -m train.register source=a.ply target=b.ply gt=gt.txt            # + errors vs GT
    python -m train.register source=a.ply target=b.ply solver=svd           # IRLS/SVD solver
    python -m train.register source=a.ply target=b.ply loss=chamfer_welsch  # any loss
    python -m train.register source=a.ply target=b.ply stages=paper         # paper's schedule

It prints the 4x4 source-to-target transform and writes ``transform.txt``,
``registered.ply`` (the whole source, transformed), ``result.json`` (loss curve, time and,
with ``gt``, the paper's errors) and ``registration.png`` (before/after) in the run folder.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from linereg.io import read_point_cloud, read_transform, write_point_cloud, write_transform
from linereg.metrics import registration_errors, rotation_error_deg
from linereg.se3 import transform_normals

from . import solvers  # noqa: F401  (registers adam_loss and svd_irls)
from .methods import MethodResult, build_method

log = logging.getLogger(__name__)

_MIN_POINTS = 3


def method_config(cfg: DictConfig) -> dict[str, Any]:
    """The registration method described by a ``register.yaml`` config."""
    common = {"num_points": cfg.num_points, "seed": cfg.seed, "progress": cfg.progress}
    if cfg.solver == "svd":
        return {
            "name": "svd_irls",
            "iterations": cfg.svd.iterations,
            **OmegaConf.to_container(cfg.svd.options),
            **common,
        }
    if cfg.solver != "adam":
        raise ValueError(f"solver must be 'adam' or 'svd', got {cfg.solver!r}")
    if cfg.loss is not None:
        loss = {"name": cfg.loss} if isinstance(cfg.loss, str) else OmegaConf.to_container(cfg.loss)
        stages = [{"loss": loss, "iterations": cfg.iterations, "lr": cfg.lr}]
    else:
        stages = cfg.stages if isinstance(cfg.stages, str) else OmegaConf.to_container(cfg.stages)
    starts = {"starts": cfg.starts, "start_angle_deg": cfg.start_angle_deg}
    return {"name": "adam_loss", "stages": stages, **starts, **common}


def register_files(cfg: DictConfig, out_dir: Path) -> tuple[MethodResult, dict[str, Any]]:
    """Run the configured registration on ``cfg.source``/``cfg.target`` and write the outputs."""
    src = read_point_cloud(cfg.source, min_points=_MIN_POINTS)
    tgt = read_point_cloud(cfg.target, min_points=_MIN_POINTS)
    gt = read_transform(cfg.gt) if cfg.gt else None
    config = method_config(cfg)
    if gt is not None:
        R_gt = torch.from_numpy(gt[:3, :3])

        def monitor(step: int, transform: np.ndarray, loss: float) -> dict[str, float]:
            # Centring the clouds changes only the translation: the rotation is already final.
            return {"err_r": float(rotation_error_deg(torch.from_numpy(transform[:3, :3]), R_gt))}

        config["monitor"] = monitor
    result = build_method(config)(src.xyz, tgt.xyz, src.normals, tgt.normals)
    transform = result.transform
    report: dict[str, Any] = {
        "source": str(cfg.source),
        "target": str(cfg.target),
        "source_points": len(src.xyz),
        "target_points": len(tgt.xyz),
        "method": {k: v for k, v in config.items() if k != "monitor"},
        "seconds": result.seconds,
        "transform": transform.tolist(),
        "loss_curve": result.info.get("loss_curve", []),
    }
    if gt is not None:
        errors = registration_errors(
            torch.from_numpy(transform)[None], torch.from_numpy(gt)[None], torch.from_numpy(src.xyz).double()[None]
        )
        report["metrics"] = {key: float(value[0]) for key, value in errors.items()}
    out_dir.mkdir(parents=True, exist_ok=True)
    write_transform(out_dir / "transform.txt", transform)
    T = torch.from_numpy(transform)
    moved = (src.xyz.astype(np.float64) @ transform[:3, :3].T + transform[:3, 3]).astype(np.float32)
    normals = (
        None if src.normals is None else transform_normals(T, torch.from_numpy(src.normals).double()).float().numpy()
    )
    write_point_cloud(out_dir / "registered.ply", moved, normals)
    (out_dir / "result.json").write_text(json.dumps(report, indent=2))
    if cfg.picture:
        from .figures import plot_registration

        plot_registration(src.xyz, tgt.xyz, transform, out_dir / "registration.png", title=Path(cfg.source).name)
    return result, report


@hydra.main(version_base="1.3", config_path="../configs/register", config_name="register")
def main(cfg: DictConfig) -> None:
    out_dir = Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    result, report = register_files(cfg, out_dir)
    np.set_printoptions(precision=6, suppress=True)
    print(f"source -> target transform ({result.seconds:.2f} s):")
    print(result.transform)
    if "metrics" in report:
        m = report["metrics"]
        print(
            f"Err_R {m['err_r_deg']:.3f} deg | Err_t l1 {m['err_t_l1']:.4g} l2 {m['err_t_l2']:.4g} "
            f"| Err_pw l1 {m['err_pw_l1']:.4g} l2 {m['err_pw_l2']:.4g}"
        )
    print(f"outputs in {out_dir}")


if __name__ == "__main__":
    main()
