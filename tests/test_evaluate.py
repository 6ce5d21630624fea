"""``python -m train.evaluate``: round trip from a training run, other datasets, figures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from linereg.checkpoint import find_checkpoint, load_checkpoint
from linereg.datasets.benchmark_pairs import run_pairs
from linereg.datasets.splits import build_split
from linereg.train import loop
from linereg.train.evaluate import Evaluation, evaluate, report
from linereg.train.figures import plot_registration, registration_figure

ROOT = Path(__file__).resolve().parent.parent


def _compose(name: str, overrides: list[str]):
    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
        return compose(name, overrides=[f"paths.root_dir={ROOT}", *overrides])


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
    assert sorted(p.name for p in (tmp_path / "figures").iterdir()) == ["pair_0000.png", "pair_0001.png"]
    table = (tmp_path / "table.md").read_text()
    assert "| identity (no motion) |" in table and "alpha=0.05" in table


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


def test_loss_at_gt_script_counts_pairs_per_loss(trained_run, capsys):
    from scripts import loss_at_gt

    run_dir, _ = trained_run
    assert loss_at_gt.main([str(run_dir), "--lines", "500"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| ") and " of 2 |" in line]
    assert len(rows) == 4 and rows[2].startswith("| chamfer (CD) |")


def test_loss_minimum_script_rows_per_loss(trained_run, capsys):
    from scripts import loss_minimum

    run_dir, _ = trained_run
    argv = [str(run_dir), "--lines", "300", "--nu0", "0.5", "2", "--iterations", "5"]
    assert loss_minimum.main(argv) == 0
    out = capsys.readouterr().out
    assert out.startswith("2 test pairs of")
    rows = [line.split(" | ") for line in out.splitlines() if line.startswith("| ") and "---" not in line]
    assert [row[0] for row in rows[1:]] == [
        "| chamfer (CD)",
        "| line metric, 300 lines, nu0 = 0.5",
        "| line metric, 300 lines, nu0 = 2",
    ]
    assert all(float(value) >= 0 for row in rows[1:] for value in row[1].split(" / "))
    assert all(row[2].endswith(" of 2 pairs") and 0 <= int(row[2].split()[0]) <= 2 for row in rows[1:])


def test_distance_to_minimum_returns_to_the_minimum_of_an_exact_copy():
    """Chamfer between a cloud and its moved copy is 0 only at the true pose: Adam finds it from 4 deg off."""
    from linereg.losses import build_loss
    from linereg.registration.solvers import Stage
    from linereg.se3 import se3_exp, transform_points
    from scripts.loss_minimum import distance_to_minimum

    generator = torch.Generator().manual_seed(0)
    src = torch.rand(200, 3, generator=generator, dtype=torch.float64) - 0.5
    gt = se3_exp(torch.tensor([[0.3, -0.2, 0.5, 0.1, 0.0, -0.1]], dtype=torch.float64))[0]
    tgt = transform_points(gt, src)
    off = se3_exp(torch.tensor([[0.05, 0.03, -0.04, 0.02, -0.01, 0.03]], dtype=torch.float64))[0] @ gt
    stage = Stage(loss={}, iterations=300, lr=0.005)
    chamfer = build_loss({"name": "chamfer"})
    err_r, err_t = distance_to_minimum(chamfer, src, tgt, gt, Stage(loss={}, iterations=0, lr=0.005), start=off)
    assert err_r > 3.5 and err_t > 0.05  # no iteration: the start itself
    err_r, err_t = distance_to_minimum(chamfer, src, tgt, gt, stage, start=off)
    assert err_r < 0.05 and err_t < 1e-3
    assert distance_to_minimum(chamfer, src, tgt, gt, stage)[0] < 0.05  # from the ground truth it stays


def test_check_iterations_script_rows_per_iteration_and_per_score(trained_run, capsys):
    from scripts import check_iterations

    run_dir, _ = trained_run
    argv = [str(run_dir), "--iterations", "3", "--lines", "300", "--draws", "0", "1", "--keep-fractions", "1", "0.5"]
    assert check_iterations.main(argv) == 0
    out = capsys.readouterr().out
    assert out.startswith("4 test pairs of")  # 2 pairs, 2 draws
    rows = [line.split(" | ") for line in out.splitlines() if line.startswith("| ") and "---" not in line]
    per_iteration = {row[0]: float(row[1]) for row in rows if "every pair" in row[0]}
    # header, 3 iterations, the bound, 8 scores (4 losses, 2 trimmed fits, RPM-Net's 2 assignment fits)
    assert len(per_iteration) == 3 and len(rows) == 1 + 3 + 1 + 4 + 2 + 2
    kept = {row[0]: row[1:] for row in rows}
    assert kept["| lowest trimmed Chamfer (keep 1) per pair"] == kept["| lowest chamfer (CD) per pair"]
    assert "| lowest assignment-weighted Chamfer per pair" in kept
    assert "| lowest Chamfer trimmed to the assignment's mass per pair" in kept
    bound = float(next(row[1] for row in rows if "a bound" in row[0]))
    assert bound <= min(per_iteration.values()) + 1e-9
    assert all(bound <= float(row[1]) + 1e-9 for row in rows if row[0].startswith("| lowest"))


def test_check_iterations_pads_a_solver_that_stopped_early():
    """FMR may stop before ``test_iters``: its later rows repeat its last estimate's, so draws line up."""
    from scripts.check_iterations import _repeat_last

    rows = torch.tensor([[3.0, 1.0], [2.0, 4.0]])
    padded = _repeat_last(rows, 4)
    assert padded.shape == (4, 2) and torch.equal(padded[:2], rows) and torch.equal(padded[2:], rows[1:].expand(2, 2))
    assert torch.equal(_repeat_last(rows, 2), rows)


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
