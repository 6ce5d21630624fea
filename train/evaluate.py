"""Evaluate a checkpoint: ``linereg-evaluate checkpoint=<file or run folder> [dataset=...]``.

Loads the model with the config stored in the checkpoint, runs it on a split of any dataset
(default: the checkpoint's own dataset, ``split=test``) and prints the paper's table (Err_R in
degrees; Err_t and Err_pw in l1 and l2, x10^-1 as the paper prints them) for the model and for
the identity (no motion) baseline, then the alpha-recall (fraction of pairs with
``Err_pw(l2) < alpha``). Writes into the run folder (``outputs/evaluate/runs/<time>/``, or
``output_dir=...``):

* ``metrics.json``: means, medians, alpha-recall, loss of the model (when the checkpoint's loss
  applies) and of the identity; the means of the registration check below (``fitness_mean``,
  ``inlier_rmse_mean``, ``confident_share``);
* ``pairs.csv``: per pair, the errors (labelled data) and the registration check
  (``fitness``, ``inlier_rmse``, ``confident``);
* ``figures/pair_XXXX.png``: before/after scatter plots of the first ``num_figures`` pairs.

The registration check is the one :func:`linereg.register` reports
(:func:`~linereg.registration.evaluation.assess_registration`): the source as evaluated, moved by
the model's estimate, against the target, with inliers within 3 sampling distances of the
target; ``inlier_rmse`` is in the units of the evaluated clouds (those of the errors). It needs
no ground truth: on unlabelled data it is what tells whether the network registered the pairs.

Iterative models (RPM-Net, FMR) are scored on the iterate chosen by the checkpoint's ``iterate``
block, or by ``iterate.rule=...`` on the command line (:mod:`linereg.registration.iterates`).
Config: ``configs/evaluate.yaml``; ``linereg-evaluate --help``.
"""

from __future__ import annotations

import csv
import json
import logging
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf, open_dict
from torch import nn
from torch.utils.data import Dataset
from tqdm.auto import tqdm

from linereg.checkpoint import load_checkpoint
from linereg.datasets.splits import build_split
from linereg.losses import build_loss
from linereg.metrics import (
    ERROR_KEYS,
    aggregate_errors,
    alpha_recall_table,
    markdown_table,
    paper_table,
    registration_errors,
)
from linereg.models import load_model
from linereg.pointcloud import scale_transform
from linereg.registration.evaluation import INLIER_DISTANCES, Assessment, assess_registration
from linereg.registration.iterates import LAST_ITERATE, IterateRule
from linereg.registry import plain
from linereg.structures import LossOutput, PairBatch
from linereg.train import CONFIG_DIR, distributed
from linereg.train.cli import reported, require, run_app

log = logging.getLogger(__name__)

COMMAND = "linereg-evaluate"

IDENTITY = "identity (no motion)"

ASSESSMENT_KEYS = ("fitness", "inlier_rmse", "confident")
"""The per-pair registration check of ``pairs.csv`` (:class:`~linereg.registration.evaluation.Assessment`)."""


@dataclass
class KeptPair:
    """One evaluated pair kept for figures (numpy, valid points only)."""

    src: np.ndarray
    tgt: np.ndarray
    transform: np.ndarray
    gt_transform: np.ndarray | None
    meta: dict[str, Any]


@dataclass
class Evaluation:
    """Results of a model on a dataset.

    Attributes:
        num_pairs: pairs evaluated.
        errors: per-pair errors ``{key: (P,)}`` (keys of ``linereg.metrics.ERROR_KEYS``), or
            ``None`` when the data has no ground truth.
        identity_errors: the same for the identity transform (the no-motion baseline).
        losses: mean loss total (``loss``) and terms (``loss/<term>``) when a loss was given.
        stats: mean loss statistics (e.g. line hits), ``stats/<name>``.
        meta: per-pair metadata, in order.
        kept: the first pairs with their estimates, for figures.
        assessments: per pair, :func:`linereg.register`'s check of the estimate
            (:func:`~linereg.registration.evaluation.assess_registration`), or ``None`` when not
            asked for.
        paths: per pair, the path of the solver's finish (``polished network``, ``solver``), when finished.
    """

    num_pairs: int = 0
    errors: dict[str, np.ndarray] | None = None
    identity_errors: dict[str, np.ndarray] | None = None
    losses: dict[str, float] = field(default_factory=dict)
    stats: dict[str, float] = field(default_factory=dict)
    meta: list[dict[str, Any]] = field(default_factory=list)
    kept: list[KeptPair] = field(default_factory=list)
    assessments: list[Assessment] | None = None
    paths: list[str] = field(default_factory=list)

    @property
    def labelled(self) -> bool:
        return self.errors is not None

    def metrics(self, alphas: Sequence[float], *, identity: bool = False) -> dict[str, float]:
        """Flat metrics: error means/medians and ``recall@<alpha>`` (model, or the identity),
        plus the loss, statistics and registration check means (model only)."""
        errors = self.identity_errors if identity else self.errors
        values = {} if errors is None else aggregate_errors(errors, alphas=alphas)
        if not identity:
            values.update(self.losses)
            values.update(self.stats)
            values.update(self.assessment_means())
        return values

    def assessment_means(self) -> dict[str, float]:
        """``fitness_mean``, ``inlier_rmse_mean`` (over the pairs with inliers; NaN without any),
        ``confident_share`` and ``check_score`` (``confident_share + fitness_mean``, the label-free score
        validation chooses checkpoints by) of the assessed pairs (empty when not assessed)."""
        if not self.assessments:
            return {}
        fitness = np.array([a.fitness for a in self.assessments])
        rmse = np.array([a.inlier_rmse for a in self.assessments])
        with_inliers = fitness > 0
        confident_share = float(np.mean([a.confident for a in self.assessments]))
        return {
            "fitness_mean": float(fitness.mean()),
            "inlier_rmse_mean": float(rmse[with_inliers].mean()) if with_inliers.any() else float("nan"),
            "confident_share": confident_share,
            "check_score": confident_share + float(fitness.mean()),
        }


def _valid(points: torch.Tensor, lengths: torch.Tensor | None, index: int) -> np.ndarray:
    """Numpy copy of the valid points of cloud ``index`` of a padded batch."""
    cloud = points[index] if lengths is None else points[index, : int(lengths[index])]
    return cloud.detach().cpu().double().numpy()


@torch.no_grad()
def evaluate_model(
    model: nn.Module,
    loader: Any,
    *,
    device: torch.device,
    loss: nn.Module | None = None,
    amp: torch.dtype | None = None,
    max_batches: int | None = None,
    keep: int = 0,
    progress: bool = False,
    description: str = "evaluate",
    iterate: IterateRule = LAST_ITERATE,
    assess: bool = False,
    finish: Any = None,
) -> Evaluation:
    """Run ``model`` (in evaluation mode) over a loader and collect errors and losses.

    Args:
        model: registration model (``PairBatch -> RegistrationOutput``).
        loader: iterable of :class:`~linereg.structures.PairBatch`.
        device: where to compute.
        loss: optional loss, averaged over batches (weighted by batch size); it receives every
            iterate as the model returns it.
        amp: autocast dtype of the forward (``None``: float32).
        max_batches: stop after this many batches.
        keep: keep the first ``keep`` pairs (clouds and estimates) for figures.
        progress: show a tqdm bar.
        description: bar label.
        iterate: the rule choosing, per pair, the iterate whose errors are measured.
        assess: also run :func:`linereg.register`'s check on every pair (:func:`assess_pairs`).
        finish: a :class:`~linereg.registration.learned.Finish`: each estimate is finished by the
            solver on the pair in its input units (:func:`finished_pairs`) before it is measured.

    Returns:
        An :class:`Evaluation`; errors only when every batch has ``gt_transform``, assessments
        only with ``assess``.
    """
    was_training = model.training
    model.eval()
    result = Evaluation(assessments=[] if assess else None)
    errors: dict[str, list[np.ndarray]] = defaultdict(list)
    identity: dict[str, list[np.ndarray]] = defaultdict(list)
    sums: dict[str, float] = defaultdict(float)
    labelled = True
    try:
        for index, batch in enumerate(tqdm(loader, desc=description, disable=not progress, leave=False)):
            if max_batches is not None and index >= max_batches:
                break
            batch: PairBatch = batch.to(device)
            with distributed.autocast(device, amp):
                output = model(batch)
            output = distributed.float32_output(output)
            size = batch.batch_size
            if loss is not None:
                _add_loss(sums, loss(output, batch), size)
            T_pred = iterate.select(
                output.transforms, batch.src_xyz, batch.tgt_xyz, batch.src_lengths, batch.tgt_lengths
            )[0].detach()
            if finish is not None:
                T_pred = finished_pairs(T_pred, batch, finish, result.paths)
            if batch.gt_transform is None:
                labelled = False
            else:
                _add_errors(errors, identity, T_pred, batch)
            if assess:
                result.assessments += assess_pairs(T_pred, batch)
            result.kept += [_kept_pair(batch, T_pred, b) for b in range(min(size, keep - len(result.kept)))]
            result.meta.extend(batch.meta if batch.meta else [{} for _ in range(size)])
            result.num_pairs += size
    finally:
        model.train(was_training)
    if result.num_pairs:
        result.losses = {k: v / result.num_pairs for k, v in sums.items() if not k.startswith("stats/")}
        result.stats = {k: v / result.num_pairs for k, v in sums.items() if k.startswith("stats/")}
    if labelled and errors:
        result.errors = {key: np.concatenate(errors[key]) for key in ERROR_KEYS}
        result.identity_errors = {key: np.concatenate(identity[key]) for key in ERROR_KEYS}
    return result


def _add_loss(sums: dict[str, float], loss_output: LossOutput, size: int) -> None:
    """Add a batch's loss total, terms (``loss/<term>``) and statistics (``stats/<name>``), weighted by ``size``."""
    sums["loss"] += float(loss_output.total) * size
    for name, value in loss_output.terms.items():
        sums[f"loss/{name}"] += float(value) * size
    for name, value in loss_output.stats.items():
        sums[f"stats/{name}"] += float(value) * size


def _add_errors(
    errors: dict[str, list[np.ndarray]], identity: dict[str, list[np.ndarray]], T_pred: torch.Tensor, batch: PairBatch
) -> None:
    """Append the errors of the estimates ``T_pred (B, 4, 4)`` and of the identity on a labelled batch."""
    eye = torch.eye(4, dtype=T_pred.dtype, device=T_pred.device).expand_as(T_pred)
    for estimate, found in ((T_pred, errors), (eye, identity)):
        for key, value in registration_errors(estimate, batch.gt_transform, batch.src_xyz, batch.src_lengths).items():
            found[key].append(value.cpu().numpy())


def assess_pairs(T_pred: torch.Tensor, batch: PairBatch) -> list[Assessment]:
    """:func:`linereg.register`'s check of each estimate ``T_pred (B, 4, 4)``, on the clouds in their
    input units (:func:`input_units`): the pair's files where its meta names them, else its valid
    points mapped back from the cube they were scaled into (numpy, on the CPU)."""
    transforms = T_pred.detach().cpu().double().numpy()
    meta = batch.meta or [{} for _ in range(batch.batch_size)]
    return [
        assess_registration(
            *input_units(
                _valid(batch.src_xyz, batch.src_lengths, b),
                _valid(batch.tgt_xyz, batch.tgt_lengths, b),
                transforms[b],
                meta[b],
            )
        )
        for b in range(batch.batch_size)
    ]


def finished_pairs(T_pred: torch.Tensor, batch: PairBatch, finish: Any, paths: list[str]) -> torch.Tensor:
    """The estimates ``T_pred (B, 4, 4)`` finished by ``finish`` on each pair in its input units
    (:func:`input_units`) and mapped back into the cube of the batch; each pair's path is appended
    to ``paths``."""
    transforms = T_pred.detach().cpu().double().numpy()
    meta = batch.meta or [{} for _ in range(batch.batch_size)]
    finished = []
    for b in range(batch.batch_size):
        src, tgt, start = input_units(
            _valid(batch.src_xyz, batch.src_lengths, b),
            _valid(batch.tgt_xyz, batch.tgt_lengths, b),
            transforms[b],
            meta[b],
        )
        result = finish(src, tgt, start)
        paths.append(result.info["path"])
        center = np.asarray(meta[b].get("center", np.zeros(3)), dtype=np.float64)
        finished.append(scale_transform(result.transform, center, float(meta[b].get("scale", 1.0))))
    return torch.as_tensor(np.stack(finished), dtype=T_pred.dtype, device=T_pred.device)


def input_units(
    src: np.ndarray, tgt: np.ndarray, transform: np.ndarray, meta: Mapping[str, Any]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(source, target, transform)`` of a pair in its input units: the files ``meta["file"]`` and
    ``meta["target_file"]`` when both are given, else ``src (N, 3)`` and ``tgt (M, 3)`` mapped back by
    ``x = x' / s + c`` (``meta["scale"]``, ``meta["center"]``; as they are without them), and
    ``transform (4, 4)`` between them."""
    from linereg.io import read_point_cloud

    scale, center = float(meta.get("scale", 1.0)), np.asarray(meta.get("center", np.zeros(3)), dtype=np.float64)
    transform = scale_transform(transform, -center * scale, 1.0 / scale)
    if "file" in meta and "target_file" in meta:
        return read_point_cloud(meta["file"]).xyz, read_point_cloud(meta["target_file"]).xyz, transform
    return src / scale + center, tgt / scale + center, transform


def _kept_pair(batch: PairBatch, T_pred: torch.Tensor, b: int) -> KeptPair:
    """Pair ``b`` of ``batch`` with its estimate, for figures."""
    return KeptPair(
        src=_valid(batch.src_xyz, batch.src_lengths, b),
        tgt=_valid(batch.tgt_xyz, batch.tgt_lengths, b),
        transform=T_pred[b].cpu().double().numpy(),
        gt_transform=None if batch.gt_transform is None else batch.gt_transform[b].cpu().double().numpy(),
        meta=dict(batch.meta[b]) if batch.meta else {},
    )


def report(name: str, evaluation: Evaluation, alphas: Sequence[float]) -> str:
    """The paper's table (model and identity rows), the alpha-recall table and the registration
    check (when assessed), as markdown."""
    check = [_check_table(name, evaluation)] if evaluation.assessments else []  # zero or one table
    if not evaluation.labelled:
        loss = evaluation.losses.get("loss")
        loss_text = f"; mean loss {loss:.4g}" if loss is not None else ""
        summary = f"{evaluation.num_pairs} pairs without ground truth: no registration errors{loss_text}."
        return "\n\n".join([summary, *check])
    summaries = {name: evaluation.metrics(alphas), IDENTITY: evaluation.metrics(alphas, identity=True)}
    return "\n".join(
        [
            f"Registration errors on {evaluation.num_pairs} pairs (means):",
            "",
            paper_table(summaries),
            "",
            "Alpha-recall (fraction of pairs with Err_pw l2 < alpha):",
            "",
            *alpha_recall_table(summaries, alphas),
            *("\n" + table for table in check),
        ]
    )


def _check_table(name: str, evaluation: Evaluation) -> str:
    """The means of the registration check of an assessed evaluation, as a markdown table."""
    means = evaluation.assessment_means()
    count = len(evaluation.assessments)
    confident = sum(check.confident for check in evaluation.assessments)
    return "\n".join(
        [
            f"Registration check of linereg.register on {count} pairs (means; inliers within "
            f"{INLIER_DISTANCES:g} sampling distances of the target):",
            "",
            *markdown_table(
                ["Method", "Fitness", "Inlier RMSE", "Confident"],
                [
                    [
                        name,
                        f"{means['fitness_mean']:.3f}",
                        f"{means['inlier_rmse_mean']:.4g}",
                        f"{means['confident_share']:.3f} ({confident}/{count})",
                    ]
                ],
            ),
        ]
    )


def _pair_name(meta: Mapping[str, Any], position: int) -> str:
    """A short readable identifier of a pair."""
    parts = [str(meta[key]) for key in ("shape", "name", "view") if key in meta]
    return "_".join(parts) if parts else f"pair{position}"


def write_evaluation(
    evaluation: Evaluation,
    out_dir: str | Path,
    *,
    name: str,
    alphas: Sequence[float],
    info: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Write ``metrics.json``, ``pairs.csv``, ``table.md`` and ``figures/`` into ``out_dir``.

    Args:
        evaluation: results of :func:`evaluate_model` (with ``keep`` pairs for figures).
        out_dir: destination folder.
        name: the model's row label.
        alphas: alpha-recall thresholds.
        info: extra entries of ``metrics.json`` (checkpoint, dataset, split, ...).

    Returns:
        The ``metrics.json`` contents.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    content = {
        **(info or {}),
        "num_pairs": evaluation.num_pairs,
        "labelled": evaluation.labelled,
        "alphas": list(alphas),
        "model": evaluation.metrics(alphas),
    }
    if evaluation.labelled:
        content["identity"] = evaluation.metrics(alphas, identity=True)
    if evaluation.labelled or evaluation.assessments is not None:
        _write_pairs(evaluation, out_dir / "pairs.csv")
    (out_dir / "metrics.json").write_text(json.dumps(content, indent=2))
    (out_dir / "table.md").write_text(report(name, evaluation, alphas) + "\n")
    if evaluation.kept:
        _write_figures(evaluation.kept, out_dir / "figures")
    return content


def _write_pairs(evaluation: Evaluation, path: Path) -> None:
    """``pairs.csv``: one row per pair with its errors and identity errors (labelled data) and its
    registration check (when assessed)."""
    error_keys = [*ERROR_KEYS, *(f"identity_{k}" for k in ERROR_KEYS)] if evaluation.labelled else []
    check_keys = list(ASSESSMENT_KEYS) if evaluation.assessments is not None else []
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["pair", *error_keys, *check_keys])
        for i, meta in enumerate(evaluation.meta):
            row = [_pair_name(meta, i)]
            if evaluation.labelled:
                row += [f"{evaluation.errors[k][i]:.6g}" for k in ERROR_KEYS]
                row += [f"{evaluation.identity_errors[k][i]:.6g}" for k in ERROR_KEYS]
            if check_keys:
                values = [getattr(evaluation.assessments[i], key) for key in ASSESSMENT_KEYS]
                row += [str(value).lower() if isinstance(value, bool) else f"{value:.6g}" for value in values]
            writer.writerow(row)


def _write_figures(pairs: Sequence[KeptPair], folder: Path) -> None:
    """Before/after scatter plots ``pair_XXXX.png`` of ``pairs``, titled with their errors."""
    from linereg.train.figures import plot_registration

    for i, pair in enumerate(pairs):
        title = _pair_name(pair.meta, i)
        if pair.gt_transform is not None:
            errors = registration_errors(
                torch.from_numpy(pair.transform)[None],
                torch.from_numpy(pair.gt_transform)[None],
                torch.from_numpy(pair.src)[None],
            )
            title += f"  Err_R {float(errors['err_r_deg'][0]):.2f} deg, Err_pw(l2) {float(errors['err_pw_l2'][0]):.4f}"
        plot_registration(pair.src, pair.tgt, pair.transform, folder / f"pair_{i:04d}.png", title=title)


def evaluate(cfg: DictConfig) -> dict[str, Any]:
    """Evaluate ``cfg.checkpoint`` on ``cfg.split`` of ``cfg.dataset``, of the run ``cfg.data_from``, or its own.

    Args:
        cfg: the composed ``configs/evaluate.yaml``.

    Returns:
        The ``metrics.json`` contents (``model``/``identity`` metrics, counts, paths, iterate rule).
    """
    if cfg.get("dataset") and cfg.get("data_from"):
        raise ValueError("give either dataset=... or data_from=..., not both")
    device = distributed.resolve_device(cfg.device, name="device")
    distributed.set_threads(cfg.threads)
    model, state = load_model(cfg.checkpoint, device)
    stored = state["config"]
    iterate = iterate_rule(stored, cfg.get("iterate"))
    data_source = load_checkpoint(cfg.data_from)["config"] if cfg.get("data_from") else stored
    with open_dict(cfg):
        if cfg.trainer.num_points is None:
            cfg.trainer.num_points = data_source["trainer"]["num_points"]
    dataset_config = plain(cfg.dataset) if cfg.get("dataset") else data_source["dataset"]
    dataset: Dataset | None = build_split(dataset_config, cfg.split, progress=cfg.progress)
    if dataset is None:
        raise ValueError(f"dataset {dataset_config.get('name')!r} has no {cfg.split!r} split")
    loss = build_loss(stored["loss"]).to(device) if cfg.with_loss else None
    if loss is not None and loss.needs_gt and not is_labelled(dataset):
        loss = None
    loader = distributed.make_loader(
        dataset,
        batch_size=cfg.batch_size,
        num_points=cfg.trainer.num_points,
        shuffle=False,
        num_workers=cfg.num_workers,
    )
    evaluation = evaluate_model(
        model,
        loader,
        device=device,
        loss=loss,
        max_batches=cfg.max_batches,
        keep=cfg.num_figures,
        progress=cfg.progress,
        iterate=iterate,
        assess=True,
        finish=_finish(cfg.get("refine")),
    )
    name = f"{stored['model']['name']} ({Path(state['path']).name})"
    output_dir = Path(cfg.output_dir)
    info = {
        "checkpoint": state["path"],
        "dataset": dataset_config.get("name"),
        "split": cfg.split,
        "epoch": state["progress"]["epoch"],
        "iterate": iterate.as_config(),
    }
    if evaluation.paths:
        info["refine"] = {path: evaluation.paths.count(path) for path in sorted(set(evaluation.paths))}
    content = write_evaluation(evaluation, output_dir, name=name, alphas=list(cfg.alphas), info=info)
    print(report(name, evaluation, list(cfg.alphas)))
    log.info("evaluation written to %s", output_dir)
    return content


def _finish(refine: Any):
    """The :class:`~linereg.registration.learned.Finish` of ``refine=`` (``true`` or solver options), or ``None``."""
    if not refine:
        return None
    from linereg.registration.learned import Finish

    return Finish(OmegaConf.to_container(refine) if OmegaConf.is_config(refine) else None)


def iterate_rule(stored: Mapping[str, Any], overrides: Mapping[str, Any] | None) -> IterateRule:
    """The iterate rule of an evaluation: the run's ``iterate`` block, with the non-null ``overrides``.

    Args:
        stored: the checkpoint's run config (:func:`linereg.models.upgrade_run_config` layout).
        overrides: the command's ``iterate`` block (``null`` entries keep the run's value).

    Raises:
        ValueError: an unknown key or a bad value, naming it.
    """
    chosen = dict(stored.get("iterate") or {})
    chosen.update({key: value for key, value in (overrides or {}).items() if value is not None})
    return IterateRule.from_config(chosen)


def is_labelled(dataset: Dataset) -> bool:
    """Whether the first pair of ``dataset`` has a ground-truth transform."""
    return len(dataset) > 0 and dataset[0].gt_transform is not None


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="evaluate")
def _evaluate_app(cfg: DictConfig) -> None:
    with reported(COMMAND):
        require(cfg, COMMAND, {"checkpoint": "a checkpoint file or run folder of linereg-train"})
        evaluate(cfg)


def main() -> None:
    """The command (``linereg-evaluate``; Hydra parses ``sys.argv``)."""
    run_app(COMMAND, _evaluate_app)


if __name__ == "__main__":
    main()
