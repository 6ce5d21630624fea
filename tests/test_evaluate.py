"""``python -m train.evaluate``: round trip from a training run, other datasets, figures."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from linereg.checkpoint import find_checkpoint, load_checkpoint
from linereg.datasets.benchmark_pairs import run_pairs
from linereg.datasets.pairs_folder import FolderPairs
from linereg.datasets.splits import build_split
from linereg.io import write_point_cloud, write_transform
from linereg.structures import PairBatch, RegistrationOutput
from linereg.train import distributed, loop
from linereg.train.evaluate import Evaluation, evaluate, evaluate_model, report
from linereg.train.figures import plot_registration, registration_figure
from tests.conftest import compose_config

ROOT = Path(__file__).resolve().parent.parent


def _compose(name: str, overrides: list[str]):
    return compose_config(name, [f"paths.root_dir={ROOT}", *overrides])


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    """A tiny RPM-Net run: (run folder, its metrics)."""
    run_dir = tmp_path_factory.mktemp("run")
    cfg = _compose(
        "train", ["debug=tiny", f"paths.output_dir={run_dir}", "model.num_neighbors=8", "loss.num_lines=300"]
    )
    return run_dir, loop.train(cfg)["metrics"]


def test_round_trip_matches_the_training_evaluation(trained_run, tmp_path):
    run_dir, train_metrics = trained_run
    cfg = _compose("evaluate", [f"checkpoint={run_dir}", f"output_dir={tmp_path}", "num_figures=2", "progress=false"])
    content = evaluate(cfg)
    assert content["num_pairs"] == 2 and content["split"] == "test" and content["labelled"]
    for key in ("err_r_deg_mean", "err_t_l2_mean", "err_pw_l1_mean", "recall@0.1"):
        assert content["model"][key] == pytest.approx(train_metrics[f"test/{key}"], rel=1e-5, abs=1e-7)
        assert content["identity"][key] == pytest.approx(train_metrics[f"test/identity/{key}"], rel=1e-6)
    assert json.loads((tmp_path / "metrics.json").read_text()) == json.loads(json.dumps(content))
    rows = (tmp_path / "pairs.csv").read_text().splitlines()
    assert rows[0].startswith("pair,err_r_deg,err_t_l1") and len(rows) == 3
    assert rows[0].endswith(",identity_err_pw_l2,fitness,inlier_rmse,confident")
    assert 0.0 <= content["model"]["fitness_mean"] <= 1.0 and "confident_share" in content["model"]
    assert sorted(p.name for p in (tmp_path / "figures").iterdir()) == ["pair_0000.png", "pair_0001.png"]
    table = (tmp_path / "table.md").read_text()
    assert "| identity (no motion) |" in table and "alpha=0.05" in table


def test_the_iterate_rule_is_the_runs_unless_overridden(trained_run, tmp_path):
    run_dir, _ = trained_run
    recorded = json.loads((run_dir / "metrics.json").read_text())["iterate"]
    common = [f"checkpoint={run_dir}", "num_figures=0", "progress=false"]
    own = evaluate(_compose("evaluate", [*common, f"output_dir={tmp_path}/own"]))
    assert own["iterate"] == recorded == {"rule": "last", "keep_fraction": 1.0}
    overridden = ["iterate.rule=best_fit", "iterate.keep_fraction=0.5", f"output_dir={tmp_path}/best"]
    best = evaluate(_compose("evaluate", [*common, *overridden]))
    assert best["iterate"] == {"rule": "best_fit", "keep_fraction": 0.5}
    assert best["identity"] == own["identity"] and best["model"]["loss"] == own["model"]["loss"]
    with pytest.raises(ValueError, match=r"iterate\.rule must be one of last, best_fit, got 'first'"):
        evaluate(_compose("evaluate", [*common, "iterate.rule=first", f"output_dir={tmp_path}/bad"]))


def test_evaluate_on_another_dataset_and_split(trained_run, tmp_path, capsys):
    run_dir, _ = trained_run
    cfg = _compose(
        "evaluate",
        [
            f"checkpoint={run_dir}/checkpoints/last.pt",
            "dataset=procedural",
            "dataset.cache_dir=null",
            "dataset.protocol.num_views=3",
            "dataset.protocol.image_size=48",
            "dataset.splits.val.num_shapes=1",
            "split=val",
            "trainer.num_points=96",
            f"output_dir={tmp_path}",
            "num_figures=0",
            "with_loss=false",
            "progress=false",
        ],
    )
    content = evaluate(cfg)
    assert content["num_pairs"] == 3 and content["split"] == "val"
    assert "loss" not in content["model"]
    assert "Err_R (deg)" in capsys.readouterr().out


def test_evaluate_on_the_test_pairs_of_another_run(trained_run, tmp_path):
    run_dir, _ = trained_run
    other = tmp_path / "other"
    other_cfg = _compose(
        "train",
        [
            "debug=tiny",
            f"paths.output_dir={other}",
            "model.num_neighbors=8",
            "loss.num_lines=300",
            "dataset.splits.test.num_shapes=2",
            "trainer.num_points=48",
        ],
    )
    loop.train(other_cfg)
    cfg = _compose(
        "evaluate", [f"checkpoint={run_dir}", f"data_from={other}", f"output_dir={tmp_path}/eval", "progress=false"]
    )
    content = evaluate(cfg)
    assert content["num_pairs"] == 4 and cfg.trainer.num_points == 48
    both = _compose("evaluate", [f"checkpoint={run_dir}", f"data_from={other}", "dataset=procedural"])
    with pytest.raises(ValueError, match=r"either dataset=\.\.\. or data_from"):
        evaluate(both)


def test_benchmark_pairs_of_a_run_are_its_test_pairs(trained_run):
    run_dir, _ = trained_run
    pairs = run_pairs(run=str(run_dir))
    state = load_checkpoint(find_checkpoint(run_dir))
    expected = build_split(state["config"]["dataset"], "test", progress=False)
    assert len(pairs) == len(expected) == 2
    np.testing.assert_array_equal(pairs[1].src_xyz, expected[1].src_xyz)
    np.testing.assert_array_equal(pairs[1].gt_transform, expected[1].gt_transform)
    assert len(run_pairs(run=str(run_dir), split="val", pairs=1)) == 1
    redrawn = run_pairs(run=str(run_dir), dataset_seed=7)  # other samples of the same pairs
    assert len(redrawn) == len(pairs) and not np.allclose(redrawn[0].src_xyz, pairs[0].src_xyz)


def _pairs_folder(folder: Path, sizes: tuple[int, ...], *, labelled: bool) -> None:
    """Pairs ``p<i>`` of anisotropic blobs of ``sizes[i]`` points away from the origin (zero padding
    lands far from them), the target a rotated and shifted copy; ``_gt.txt`` files when ``labelled``."""
    rng = np.random.default_rng(0)
    folder.mkdir()
    angle = np.deg2rad(30.0)
    gt = np.eye(4)
    gt[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    gt[:3, 3] = [0.2, -0.1, 0.3]
    for i, size in enumerate(sizes):
        cloud = rng.normal(size=(size, 3)) * [1.0, 0.6, 0.3] + 5.0
        write_point_cloud(folder / f"p{i}_src.ply", cloud)
        write_point_cloud(folder / f"p{i}_tgt.ply", cloud @ gt[:3, :3].T + gt[:3, 3])
        if labelled:
            write_transform(folder / f"p{i}_gt.txt", gt)


class _GroundTruthModel(nn.Module):
    """Answers each pair's ground truth, moved by ``offset`` (a wrong estimate when not zero)."""

    def __init__(self, offset: float) -> None:
        super().__init__()
        self.offset = offset

    def forward(self, batch: PairBatch) -> RegistrationOutput:
        estimate = batch.gt_transform.clone()
        estimate[:, 0, 3] += self.offset
        return RegistrationOutput(transforms=[estimate])


def test_the_registration_check_tells_a_right_estimate_from_a_wrong_one(tmp_path):
    _pairs_folder(tmp_path / "pairs", (150, 200), labelled=True)
    loader = distributed.make_loader(
        FolderPairs(tmp_path / "pairs"), batch_size=2, num_points=None, shuffle=False
    )  # one padded batch: the 150-point pair has src_lengths 150
    right, wrong = (
        evaluate_model(_GroundTruthModel(offset), loader, device=torch.device("cpu"), assess=True)
        for offset in (0.0, 1.5)
    )
    assert [a.confident for a in right.assessments] == [True, True]
    assert all(a.fitness > 0.99 and a.inlier_rmse < 1e-4 for a in right.assessments)
    assert [a.confident for a in wrong.assessments] == [False, False]
    assert right.metrics([0.1])["confident_share"] == 1.0 and wrong.metrics([0.1])["confident_share"] == 0.0
    assert evaluate_model(_GroundTruthModel(0.0), loader, device=torch.device("cpu")).assessments is None


def test_evaluate_checks_the_registration_of_unlabelled_pairs(trained_run, tmp_path, capsys):
    run_dir, _ = trained_run
    _pairs_folder(tmp_path / "pairs", (120, 120, 120), labelled=False)
    overrides = ["dataset=pairs_folder", f"dataset.root={tmp_path / 'pairs'}", "dataset.splits.test={}"]
    cfg = _compose(
        "evaluate",
        [f"checkpoint={run_dir}", *overrides, f"output_dir={tmp_path}/eval", "num_figures=0", "progress=false"],
    )
    content = evaluate(cfg)
    assert not content["labelled"] and {"fitness_mean", "inlier_rmse_mean", "confident_share"} <= set(content["model"])
    with open(tmp_path / "eval" / "pairs.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert list(rows[0]) == ["pair", "fitness", "inlier_rmse", "confident"] and len(rows) == 3
    assert all(0.0 <= float(row["fitness"]) <= 1.0 and row["confident"] in ("true", "false") for row in rows)
    shares = np.mean([row["confident"] == "true" for row in rows])
    assert content["model"]["confident_share"] == pytest.approx(shares)
    printed = capsys.readouterr().out
    assert "3 pairs without ground truth" in printed and "| Method | Fitness | Inlier RMSE | Confident |" in printed


def test_report_of_unlabelled_data():
    text = report("model", Evaluation(num_pairs=3, losses={"loss": 0.25}), [0.1])
    assert text == "3 pairs without ground truth: no registration errors; mean loss 0.25."


def test_plot_registration_writes_a_png(tmp_path):
    rng = np.random.default_rng(0)
    src = rng.normal(size=(300, 3))
    T = np.eye(4)
    T[:3, 3] = [0.5, 0.0, 0.0]
    path = plot_registration(torch.from_numpy(src), src + T[:3, 3], T, tmp_path / "sub" / "pair.png", title="t")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    figure = registration_figure(src, src, T)
    assert len(figure.axes) == 2
    with pytest.raises(ValueError, match=r"T must have shape \(4, 4\)"):
        registration_figure(src, src, np.eye(3))


@pytest.mark.parametrize("offset", [0.0, 0.4])
def test_evaluate_judges_a_pair_as_register_does_in_its_input_units(tmp_path, offset):
    """The pairs are scaled into a cube for the network; the check maps the estimate back and judges
    it on the pair's files with register's function, so both commands give one verdict and one RMSE."""
    from linereg.io import read_point_cloud, read_transform
    from linereg.registration.api import quality
    from linereg.train.evaluate import assess_pairs

    _pairs_folder(tmp_path / "pairs", (300,), labelled=True)
    pair = FolderPairs(tmp_path / "pairs", half_extent=1.0).make_pair(0)
    assert pair.meta["scale"] != 1.0
    loader = distributed.make_loader(
        FolderPairs(tmp_path / "pairs", half_extent=1.0), batch_size=1, num_points=None, shuffle=False
    )
    batch = next(iter(loader))
    estimate = batch.gt_transform.clone().double()
    estimate[:, 0, 3] += offset
    (judged,) = assess_pairs(estimate, batch)
    truth = read_transform(tmp_path / "pairs" / "p0_gt.txt")
    in_units = truth.copy()
    in_units[0, 3] += offset / pair.meta["scale"]
    source, target = (read_point_cloud(tmp_path / "pairs" / f"p0_{side}.ply").xyz for side in ("src", "tgt"))
    registered = quality(source, target, in_units)
    assert judged.confident == registered["confident"] == (offset == 0.0)
    assert judged.inlier_rmse == pytest.approx(registered["inlier_rmse"], rel=1e-4, abs=1e-6)
    assert judged.fitness == pytest.approx(registered["fitness"])


def test_refine_finishes_each_estimate_in_input_units(tmp_path):
    """A network 4 degrees off: the solver's finish on the pair in its own units brings every pair back."""
    from linereg.registration.learned import Finish

    _pairs_folder(tmp_path / "pairs", (300, 300), labelled=True)
    loader = distributed.make_loader(
        FolderPairs(tmp_path / "pairs", half_extent=1.0), batch_size=2, num_points=None, shuffle=False
    )

    class _Off(nn.Module):
        def forward(self, batch: PairBatch) -> RegistrationOutput:
            turn = torch.eye(4, dtype=batch.gt_transform.dtype).repeat(batch.batch_size, 1, 1)
            angle = torch.tensor(np.radians(4.0), dtype=turn.dtype)
            turn[:, 0, 0], turn[:, 0, 1], turn[:, 1, 0], turn[:, 1, 1] = (
                angle.cos(),
                -angle.sin(),
                angle.sin(),
                angle.cos(),
            )
            return RegistrationOutput(transforms=[turn @ batch.gt_transform])

    bare = evaluate_model(_Off(), loader, device=torch.device("cpu"))
    finished = evaluate_model(_Off(), loader, device=torch.device("cpu"), finish=Finish(), assess=True)
    assert bare.errors["err_r_deg"].min() > 3.9
    assert finished.errors["err_r_deg"].max() < 0.05 and finished.paths == ["polished network"] * 2
    assert all(a.confident for a in finished.assessments)
