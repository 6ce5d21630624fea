"""``scripts/studies/``: the index lists every study script, and the ones that read a training run
print their tables (tests/test_scripts.py starts every script)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch

from linereg.train import loop

ROOT = Path(__file__).resolve().parent.parent
STUDIES = ROOT / "scripts" / "studies"
SCRIPTS = sorted(path.stem for path in STUDIES.glob("*.py"))


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory, hydra_compose):
    """A tiny RPM-Net run folder."""
    run_dir = tmp_path_factory.mktemp("run")
    overrides = ["debug=tiny", f"paths.output_dir={run_dir}", "model.num_neighbors=8", "loss.num_lines=300"]
    cfg = hydra_compose("train", [f"paths.root_dir={ROOT}", *overrides])
    loop.train(cfg)
    return run_dir


def test_the_index_lists_every_study_script_and_its_page():
    index = (STUDIES / "README.md").read_text()
    listed = {line.split("`")[1].removesuffix(".py") for line in index.splitlines() if line.startswith("| `")}
    assert listed == set(SCRIPTS)
    pages = re.findall(r"\]\(([^)]+\.md)\)", index)
    assert len(pages) == len(SCRIPTS) and all((STUDIES / page).resolve().is_file() for page in pages)


def test_loss_at_gt_script_counts_pairs_per_loss(trained_run, capsys):
    from scripts.studies import loss_at_gt

    assert loss_at_gt.main([str(trained_run), "--lines", "500"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| ") and " of 2 |" in line]
    assert len(rows) == 4 and rows[2].startswith("| chamfer (CD) |")


def test_loss_minimum_script_rows_per_loss(trained_run, capsys):
    from scripts.studies import loss_minimum

    argv = [str(trained_run), "--lines", "300", "--nu0", "0.5", "2", "--iterations", "5"]
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
    from scripts.studies.loss_minimum import distance_to_minimum

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
    from scripts.studies import check_iterations

    run = str(trained_run)
    argv = [run, "--iterations", "3", "--lines", "300", "--draws", "0", "1", "--keep-fractions", "1", "0.5"]
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
    from scripts.studies.check_iterations import _repeat_last

    rows = torch.tensor([[3.0, 1.0], [2.0, 4.0]])
    padded = _repeat_last(rows, 4)
    assert padded.shape == (4, 2) and torch.equal(padded[:2], rows) and torch.equal(padded[2:], rows[1:].expand(2, 2))
    assert torch.equal(_repeat_last(rows, 2), rows)


def _fragment_record(pair: int, method: str, rotation: float, translation: float) -> dict:
    meta = {"tgt_fragment": pair, "src_fragment": pair + 5, "overlap_bin": "[0.3, 0.5)", "overlap": 0.4}
    return {"pair": pair, "method": method, "err_r_deg": rotation, "err_t_l2": translation, "meta": meta}


def test_failed_fragment_pairs_are_those_one_method_misses():
    from scripts.studies.check_failed_fragment_pairs import failed_pairs

    records = [_fragment_record(0, "ours", 1.0, 0.02), _fragment_record(0, "fpfh_ransac", 1.0, 0.02)]
    records += [_fragment_record(1, "ours", 1.0, 0.02), _fragment_record(1, "fpfh_ransac", 1.0, 0.11)]
    records += [_fragment_record(2, "ours", 6.0, 0.02), _fragment_record(2, "fricp", 90.0, 2.0)]

    failed = failed_pairs(records, ["ours", "fpfh_ransac"])

    assert list(failed) == [1, 2] and set(failed[1]) == {"ours", "fpfh_ransac"}


def test_the_chain_goes_through_the_fragment_overlapping_both_ends_most():
    import numpy as np

    from linereg.datasets.fragments import Fragments
    from scripts.studies.check_failed_fragment_pairs import chain_fragment

    pairs = np.array([[0, 1], [0, 2], [0, 3], [1, 3], [2, 3]])
    fragments = Fragments(
        xyz=[np.zeros((1, 3))] * 4,
        normals=[np.zeros((1, 3))] * 4,
        frames=np.zeros((4, 2), dtype=np.int64),
        poses=np.tile(np.eye(4), (4, 1, 1)),
        pairs=pairs,
        overlaps=np.array([0.9, 0.5, 0.3, 0.2, 0.6]),
    )

    assert chain_fragment(fragments, 0, 3) == (2, 0.5, 0.6)  # fragment 1 overlaps 3 by 0.2 only


def test_a_failure_is_search_or_ambiguity_by_the_fine_scores():
    from scripts.studies.check_failed_fragment_pairs import failures, verdict_table

    def row(pair: int, scores: list[float]) -> dict:
        truth = [0.30, 0.70, 0.60, 0.50]
        return {
            "pair": pair,
            "bin": "[0.3, 0.5)",
            "errors": {"ours": (20.0, 80.0)},
            "scores": {"truth": truth, "ours": scores},
        }

    rows = [row(0, [0.20, 0.80, 0.50, 0.40]), row(1, [0.35, 0.65, 0.70, 0.60]), row(2, [0.35, 0.75, 0.5, 0.4])]

    assert [verdict for _, _, verdict in failures(rows, ["ours"])] == ["search", "ambiguity", "mixed"]
    assert "| ours | [0.3, 0.5) | 3 | 1 | 1 | 1 |" in verdict_table(rows, ["ours"])


def test_the_demo_pair_is_redkitchen_fragment_6_onto_fragment_0(shared_data):
    import numpy as np

    from scripts.studies.check_3dmatch_ground_truth import load
    from scripts.studies.check_fragment_ground_truth import pose_gap

    data = load(shared_data)

    published = data["published"]
    angle, centimetres = pose_gap(published[(0, 4)] @ published[(4, 6)], published[(0, 6)])
    assert angle < 0.01 and centimetres < 0.01  # one trajectory: the published poses chain exactly
    assert np.allclose(pose_gap(published[(0, 6)], published[(0, 6)]), 0.0, atol=1e-5)


@pytest.mark.shared_data
def test_finish_costs_adds_up_the_parts_of_the_finished_network(shared_data):
    """The modelled time of the finished network is the sum of its parts, and the bound (every part
    but the fallback's solver free) is never below the modelled ratio."""
    from scripts.studies.finish_costs import costs

    row = costs("rpm_ours_airplane", "rpm_ours_airplane", 2)
    parts = row["forward"] + row["polish"] + row["check"] + row["fallback"] + row["wrap"]
    assert row["finished"] == pytest.approx(parts) and row["ratio"] == pytest.approx(row["solver_way"] / parts)
    assert 0.0 <= row["fallback_share"] <= 1.0 and row["bound"] >= row["ratio"] and row["share_for_target"] >= 0.0
    assert min(row[name] for name in ("solver_way", "solver", "forward", "polish", "check")) > 0.0
    assert 0.0 <= row["truth_trusted"] <= 1.0 and row["perfect_ratio"] > 0.0


@pytest.mark.shared_data
def test_a_stricter_acceptance_never_keeps_more_polished_poses(shared_data):
    """``--acceptance``: each rule adds a test to the check, so the solver runs at least as often as
    under the check alone; the solver's own row runs it on every pair."""
    from scripts.studies.finish_costs import RULES, acceptance

    rows = acceptance("rpm_ours_airplane", "val", 3)
    check, *stricter = (rows[name]["solver_ran"] for name in RULES)
    assert all(check <= ran for ran in stricter) and rows["the solver alone"]["solver_ran"] == 1.0
    assert all(row["err_r_deg_mean"] >= 0.0 for row in rows.values())


@pytest.mark.shared_data
def test_the_iterations_study_runs_the_network_at_each_count(shared_data, monkeypatch):
    """``--iterations``: one row per count, each forward at that count (the model's own restored after)."""
    from linereg.registration.learned import LearnedRegistration
    from scripts.studies import finish_costs

    monkeypatch.setattr(finish_costs, "ITERATIONS", (5, 1))
    rows = finish_costs.iterations("rpm_ours_airplane", "val", 2)
    assert list(rows) == [5, 1] and all(0 <= row["trusted"] <= row["pairs"] == 2 for row in rows.values())
    assert rows[1]["forward_s"] < rows[5]["forward_s"]
    assert LearnedRegistration("rpm_ours_airplane").model.test_iters == 5


def test_the_finish_runs_fewer_network_iterations(monkeypatch):
    """RPM-Net finished by the solver runs :data:`FINISH_ITERATIONS`; bare, its own; a count asked for wins."""
    import torch

    from linereg.models.rpmnet import RPMNet
    from linereg.registration import learned

    model = RPMNet(num_neighbors=8).eval()
    seen = []
    forward = RPMNet.forward
    monkeypatch.setattr(RPMNet, "forward", lambda self, batch: seen.append(self.test_iters) or forward(self, batch))
    state = {"path": "m.pt", "config": {"trainer": {"num_points": 32}}, "half_extent": None}
    monkeypatch.setattr(learned, "_loaded", lambda checkpoint, device: (model, state))
    cloud = torch.rand(64, 3, generator=torch.Generator().manual_seed(0)).double().numpy()
    for options, count in (({}, 5), ({"refine": True}, learned.FINISH_ITERATIONS), ({"iterations": 3}, 3)):
        learned.LearnedRegistration("m.pt", **options).predict_many([(cloud, cloud)])
        assert seen[-1] == count and model.test_iters == 5
    with pytest.raises(ValueError, match="iterations=0"):
        learned.LearnedRegistration("m.pt", iterations=0)


def test_check_trust_measures_the_method_it_is_given(monkeypatch):
    """``check_trust.py --method ... --refine``: the pair is registered by that method, finished."""
    from types import SimpleNamespace

    import linereg
    from scripts.studies import check_trust

    calls = []
    register = linereg.register

    def spy(src, tgt, **options):
        calls.append(options)
        return register(src, tgt, method="icp_point")

    monkeypatch.setattr(check_trust.linereg, "register", spy)
    rng = np.random.default_rng(0)
    cloud = rng.normal(size=(600, 3)) * [1.0, 0.6, 0.3]
    pair = SimpleNamespace(src_xyz=cloud, tgt_xyz=cloud + 0.01, gt_transform=np.eye(4))
    pair.gt_transform[:3, 3] = 0.01
    row = check_trust.measure("airplane", 0, pair, "rpm_ours_objects", refine=True)
    assert calls == [{"method": "rpm_ours_objects", "refine": True}]
    assert row["right"] and row["source"] == "airplane" and isinstance(row["confident"], bool)
    assert check_trust.measure("airplane", 0, pair)["right"] and calls[-1] == {"method": "robust"}
