"""Register one pair of point clouds: ``linereg-register source=a.ply target=b.ply``.

A thin command around :func:`linereg.register` (also ``python -m train.register`` in a checkout).
Hydra overrides select everything else (``configs/register/register.yaml``; the app has its own
config root so that ``loss=...`` names a loss, not the training configs' ``loss`` group)::

    python -m train.register source=a.ply target=b.ply                      # method=robust
    python -m train.register source=a.ply target=b.ply gt=gt.txt            # + errors vs GT
    python -m train.register source=a.ply target=b.ply init=odom.txt        # initial guess
    python -m train.register source=a.ply target=b.ply picture=true         # + before/after PNG
    python -m train.register source=a.ply target=b.ply method=adam_loss     # Adam schedules
    python -m train.register source=a.ply target=b.ply method=svd_irls      # IRLS/SVD solver
    python -m train.register source=a.ply target=b.ply method=icp_point     # any registered method
    python -m train.register source=a.ply target=b.ply method=rpm_ours_airplane refine=true  # a network
    python -m train.register scans=scans/ mode=unordered gt=scans.conf  # many scans into one frame

``method=`` takes what :func:`linereg.register` takes: a name of
:data:`linereg.registration.METHODS` (the settings of ``robust``, ``adam_loss`` and ``svd_irls``
come from the config), a pretrained name, or a checkpoint file / run folder of ``python -m train``.

It prints the 4x4 source-to-target transform with Open3D's ``fitness`` and ``inlier_rmse`` and a
``confident`` flag, and writes ``transform.txt``, ``registered.ply`` (the whole source,
transformed) and ``result.json`` (those values, time and, with ``gt``, the paper's errors) in
the run folder; ``registration.png`` with ``picture=true``. A failed run leaves no folder.
"""

from __future__ import annotations

import json
import sys
import warnings
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from omegaconf import DictConfig, ListConfig, OmegaConf

from linereg.train import CONFIG_DIR
from linereg.train.cli import fail, reported, require, run_app

COMMAND = "linereg-register"


class RegisterError(ValueError):
    """A bad argument of the register command; the message names it."""


def parse_init(value: Any) -> np.ndarray | None:
    """The ``init=`` argument as a ``(4, 4)`` rigid transform (``None`` when not given).

    Accepts a file (:func:`read_rigid`), 16 (4x4) or 12 (3x4) numbers as a list or a string
    separated by spaces or commas, or ``identity``. A nearly rigid matrix is orthonormalised with a
    warning (:func:`linereg.checks.as_rigid_transform`).

    Raises:
        RegisterError: not a file, not 12/16 numbers, or not rigid; the message names ``init``.
    """
    from linereg.checks import as_rigid_transform
    from linereg.io import homogeneous_matrix

    if value is None:
        return None
    if isinstance(value, str) and value.strip().lower() == "identity":
        return np.eye(4)
    if isinstance(value, str) and Path(value).expanduser().exists():
        return read_rigid(value, "init")
    numbers = list(value) if isinstance(value, list | tuple | ListConfig) else str(value).replace(",", " ").split()
    try:
        values = np.array([float(number) for number in numbers], dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise RegisterError(
            f"init={value!r}: not a file and not a list of numbers (give a 4x4 transform file or 16 numbers)"
        ) from error
    try:
        return as_rigid_transform(homogeneous_matrix(values), "init")
    except ValueError as error:
        raise RegisterError(f"init={value!r}: {error}") from error


def read_similarity(path: Any, argument: str) -> np.ndarray:
    """The transform file of ``argument`` as a ``(4, 4)`` similarity ``[s R | t]`` (``scale=true``'s
    ground truth): its block divided by the cube root of its determinant must be rigid.

    Raises:
        RegisterError: missing, unreadable, a reflection or not a similarity; the message names ``argument``.
    """
    from linereg.checks import as_rigid_transform
    from linereg.io import read_transform

    try:
        matrix = read_transform(Path(str(path)).expanduser(), rigid=False)
        scale = float(np.cbrt(np.linalg.det(matrix[:3, :3])))
        if not scale > 0:
            raise ValueError("its 3x3 block has no positive determinant (not a rotation times a scale)")
        rigid = as_rigid_transform(matrix @ np.diag([1 / scale, 1 / scale, 1 / scale, 1.0]), argument)
    except (OSError, ValueError) as error:
        raise RegisterError(f"{argument}={path}: {error}") from error
    return rigid @ np.diag([scale, scale, scale, 1.0])


def read_rigid(path: Any, argument: str) -> np.ndarray:
    """The transform file of ``argument`` (``gt``, ``init``: ``.txt``, ``.npy`` or ``.npz``) as an
    exactly rigid ``(4, 4)``; a nearly rigid one is orthonormalised with a warning naming ``argument``.

    Raises:
        RegisterError: missing, a folder, unreadable or not rigid; the message names ``argument``.
    """
    from linereg.checks import as_rigid_transform
    from linereg.io import read_transform

    try:
        return as_rigid_transform(read_transform(Path(str(path)).expanduser()), argument)
    except (OSError, ValueError) as error:
        raise RegisterError(f"{argument}={path}: {error}") from error


def warn(note: str) -> None:
    """Write ``linereg-register: warning: <note>`` (one line) to stderr."""
    print(f"{COMMAND}: warning: {' '.join(note.split())}", file=sys.stderr)


def read_cloud(path: Any, argument: str):
    """:func:`linereg.registration.api.read_cloud_file` (the library's check) with errors as :class:`RegisterError`."""
    from linereg.registration.api import read_cloud_file

    if path is None or str(path) in ("", "???"):
        raise RegisterError(f"{argument}= is required (a point-cloud file)")
    try:
        return read_cloud_file(str(path), argument)
    except (FileNotFoundError, ValueError) as error:
        raise RegisterError(str(error)) from error


def method_config(cfg: DictConfig) -> dict[str, Any] | str:
    """The registration method of a ``register.yaml`` config: a registered method that reads the
    command's settings (``from_register_settings``: ``robust``, ``adam_loss``, ``svd_irls``) as the
    method config it builds from them; any other ``method`` (a registered name, a pretrained name or
    a checkpoint) as it is."""
    from linereg.registration import METHODS

    name = str(cfg.method)
    reader = getattr(METHODS.get(name), "from_register_settings", None) if name in METHODS else None
    if reader is None:
        return name
    try:
        return reader(OmegaConf.to_container(cfg))
    except ValueError as error:
        raise RegisterError(str(error)) from error


def register_files(cfg: DictConfig, out_dir: Path) -> tuple[Any, dict[str, Any]]:
    """Run :func:`linereg.register` on ``cfg.source``/``cfg.target`` as configured and write the outputs.

    Everything is read and checked before the solver runs; ``out_dir`` is written only at the end.

    Returns:
        ``(result, report)``: the :class:`~linereg.registration.RegistrationResult` and the
        contents of ``result.json``.

    Raises:
        RegisterError: a bad argument or file, naming it.
    """
    src = read_cloud(cfg.source, "source")
    tgt = read_cloud(cfg.target, "target")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gt = (read_similarity if cfg.scale else read_rigid)(cfg.gt, "gt") if cfg.gt else None
        init = parse_init(cfg.init)
    input_notes = _notes(caught)
    if cfg.picture and find_spec("matplotlib") is None:
        raise RegisterError(
            "picture=true needs matplotlib, which comes with the [train] extra: pip install 'linereg[train]'"
        )
    result, notes = _register(cfg, src, tgt, init, gt)
    report = _report(cfg, src, tgt, result, input_notes + notes, gt)
    _write_outputs(cfg, out_dir, src, tgt, result.transformation, report)
    return result, report


def _register(cfg: DictConfig, src, tgt, init: np.ndarray | None, gt: np.ndarray | None) -> tuple[Any, list[str]]:
    """:func:`linereg.register` as configured; the result and the warnings it gave."""
    from linereg.registration import register

    config = method_config(cfg)
    if gt is not None and isinstance(config, dict) and config["name"] != "robust":
        config["monitor"] = _rotation_monitor(gt)
    options = {"refine": OmegaConf.to_container(cfg.refine) if OmegaConf.is_config(cfg.refine) else cfg.refine}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            result = register(
                src,
                tgt,
                init=init,
                method=config,
                device=cfg.device,
                fitness_threshold=cfg.fitness_threshold,
                scale=cfg.scale,
                **(options if cfg.refine else {}),
            )
        except (KeyError, TypeError, ValueError) as error:
            raise RegisterError(str(error)) from error
    notes = _notes(caught)
    for note in result.info.get("warnings", ()):
        warn(note)
    return result, notes + list(result.info.get("warnings", ()))


def _notes(caught: list[warnings.WarningMessage]) -> list[str]:
    """The messages of the ``UserWarning``s among ``caught``, each written with :func:`warn`."""
    notes = [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    for note in notes:
        warn(note)
    return notes


def _rotation_monitor(gt: np.ndarray):
    """A solver monitor reporting the rotation error against the ground truth ``gt (4, 4)``."""
    import torch

    from linereg.metrics import rotation_error_deg

    R_gt = torch.from_numpy(gt[:3, :3])

    def monitor(step: int, transform: np.ndarray, loss: float) -> dict[str, float]:
        # Centring the clouds changes only the translation: the rotation is already final.
        return {"err_r": float(rotation_error_deg(torch.from_numpy(transform[:3, :3]), R_gt))}

    return monitor


def _report(cfg: DictConfig, src, tgt, result, notes: list[str], gt: np.ndarray | None) -> dict[str, Any]:
    """The contents of ``result.json``: clouds, method, time, transform, quality, the solver's record
    (``solver``: :attr:`~linereg.registration.robust_result.RobustResult.summary`, when the method has
    one) and (with ``gt``) errors."""
    transform = result.transformation
    info = dict(result.info)
    info.pop("warnings", None)
    quality = {key: info.pop(key) for key in ("fitness_threshold", "sampling_distance", "init") if key in info}
    report: dict[str, Any] = {
        "source": str(cfg.source),
        "target": str(cfg.target),
        "source_points": len(src.xyz),
        "target_points": len(tgt.xyz),
        "method": info.pop("method"),
        "seconds": result.seconds,
        "transform": transform.tolist(),
        "fitness": result.fitness,
        "inlier_rmse": result.inlier_rmse,
        "confident": result.confident,
        "scale": result.scale,
        **quality,
        "info": info,
        "warnings": notes,
    }
    if result.solution is not None:
        report["solver"] = result.solution.summary
    if gt is not None:
        import torch

        from linereg.metrics import registration_errors

        gt_scale = float(np.cbrt(np.linalg.det(gt[:3, :3])))
        unscaled = [
            matrix @ np.diag([1 / s, 1 / s, 1 / s, 1.0]) for matrix, s in ((transform, result.scale), (gt, gt_scale))
        ]
        errors = registration_errors(
            torch.from_numpy(unscaled[0])[None],
            torch.from_numpy(unscaled[1])[None],
            gt_scale * torch.from_numpy(src.xyz).double()[None],
        )
        report["metrics"] = {key: float(value[0]) for key, value in errors.items()}
        report["metrics"]["scale_error"] = result.scale / gt_scale - 1.0
    return report


def _write_outputs(cfg: DictConfig, out_dir: Path, src, tgt, transform: np.ndarray, report: dict[str, Any]) -> None:
    """``transform.txt``, ``registered.ply``, ``result.json`` (and ``registration.png``) in ``out_dir``."""
    from linereg.io import write_point_cloud, write_transform

    out_dir.mkdir(parents=True, exist_ok=True)
    write_transform(out_dir / "transform.txt", transform)
    moved = (src.xyz.astype(np.float64) @ transform[:3, :3].T + transform[:3, 3]).astype(np.float32)
    normals = None if src.normals is None else (src.normals @ transform[:3, :3].T).astype(np.float32)
    write_point_cloud(out_dir / "registered.ply", moved, normals)
    (out_dir / "result.json").write_text(json.dumps(report, indent=2, default=float))
    if cfg.picture:
        from linereg.train.figures import plot_registration

        plot_registration(src.xyz, tgt.xyz, transform, out_dir / "registration.png", title=Path(cfg.source).name)


def _register_pairs(cfg: DictConfig, out_dir: Path) -> None:
    """``pairs=<folder>``: :func:`~linereg.train.register_pairs.register_folder`, and a summary line."""
    from linereg.train.register_pairs import register_folder

    for key in ("source", "target", "gt", "init"):
        if cfg[key] is not None:
            raise RegisterError(f"{key}= is for one pair; pairs=<folder> reads each pair's files (and <name>_gt.txt)")
    if cfg.scale:
        raise RegisterError("scale=true is for one pair (source=, target=), not pairs=<folder>")
    try:
        summary = register_folder(cfg, out_dir, method_config(cfg))
    except (FileNotFoundError, ValueError, TypeError) as error:
        raise RegisterError(f"pairs={cfg.pairs}: {error}") from error
    print(
        f"{summary['registered']} pairs registered ({summary['skipped']} already in the table), "
        f"{summary['confident']} confident: {summary['table']}"
    )


def _register_scans(cfg: DictConfig, out_dir: Path) -> None:
    """``scans=<folder>``: :func:`~linereg.train.register_scans.register_folder_scans`, and a summary."""
    from linereg.train.register_scans import register_folder_scans

    for key in ("source", "target", "init", "pairs"):
        if cfg[key] is not None:
            raise RegisterError(f"{key}= is not for scans=<folder>, which registers the folder's scans with each other")
    if cfg.scale:
        raise RegisterError("scale=true is for one pair (source=, target=), not scans=<folder>")
    summary = register_folder_scans(cfg, out_dir, method_config(cfg))
    print(
        f"{summary['placed']} of {summary['scans']} scans placed; {summary['edges']} edges "
        f"({summary['registered']} registered, {summary['resumed']} already in edges.csv), "
        f"{summary['seconds_per_edge']:.2f} s per edge, {summary['seconds']:.1f} s in all"
    )
    if summary["errors"] is not None:
        rotation, translation = summary["errors"]
        print(f"largest error of a placed scan against gt: {rotation:.3f} deg, {translation:.4g} (input units)")
    print(f"outputs in {out_dir}: poses.txt, edges.csv, scans.csv, merged.ply")


@hydra.main(version_base="1.3", config_path=f"{CONFIG_DIR}/register", config_name="register")
def _register_app(cfg: DictConfig) -> None:
    out_dir = Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    with reported(COMMAND):
        require(cfg, COMMAND, {})
        if cfg.pairs is not None:
            _register_pairs(cfg, out_dir)
            return
        if cfg.scans is not None:
            _register_scans(cfg, out_dir)
            return
        missing = [f"{key}=... (a point-cloud file)" for key in ("source", "target") if cfg[key] is None]
        if missing:
            fail(COMMAND, f"missing {', '.join(missing)}, pairs=<folder> or scans=<folder>; see {COMMAND} --help")
        result, report = register_files(cfg, out_dir)
    np.set_printoptions(precision=6, suppress=True)
    print(f"source -> target transform ({result.seconds:.2f} s):")
    print(result.transformation)
    flag = "confident" if result.confident else "NOT confident: the pose may be wrong (warnings above)"
    scale = f"scale {result.scale:.6g} | " if cfg.scale else ""
    print(f"{scale}fitness {result.fitness:.3f} | inlier_rmse {result.inlier_rmse:.4g} | {flag}")
    if "metrics" in report:
        m = report["metrics"]
        print(
            f"Err_R {m['err_r_deg']:.3f} deg | translation error {m['err_t_l2']:.4g} "
            f"| Err_pw l1 {m['err_pw_l1']:.4g} l2 {m['err_pw_l2']:.4g}"
            + (f" | scale error {100 * m['scale_error']:+.3f} %" if cfg.scale else "")
        )
    print(f"outputs in {out_dir}")


def main() -> None:
    """The command (``linereg-register``; Hydra parses ``sys.argv``)."""
    run_app(COMMAND, _register_app)


if __name__ == "__main__":
    main()
