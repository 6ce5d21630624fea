"""Real-scan benchmark: the ``3dmatch`` pair source on 3DMatch-layout folders, and the recall,
overlap-bin and confidence reports of registration/benchmark_results.py."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from linereg.datasets.benchmark_pairs import threedmatch_pairs
from linereg.io import write_point_cloud
from linereg.registration.benchmark_results import (
    IDENTITY,
    confidence_lines,
    confusion,
    identity_records,
    is_correct,
    overlap_bin,
    pooled_records,
    recall_key,
    recall_sections,
    summarize_records,
)
from linereg.registration.methods import MethodResult
from linereg.structures import PairSample
from linereg.train import benchmark as benchmark_module
from linereg.train.benchmark import run_benchmark, write_results
from scripts import bench_confidence

# ----------------------------------------------------------------------------- 3DMatch layout


def _log_block(i: int, j: int, n: int, transform: np.ndarray) -> str:
    rows = "\n".join(" ".join(f"{v:.10f}" for v in row) for row in transform)
    return f"{i}\t{j}\t{n}\n{rows}\n"


def _pose(rng: np.random.Generator) -> np.ndarray:
    """A fragment-to-world pose: rotation up to ~20 deg, translation up to 0.5 m."""
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * 0.2).as_matrix()
    pose[:3, 3] = rng.uniform(-0.5, 0.5, 3)
    return pose


def _write_scene(scene: Path, log_folder: Path, *, seed: int, fragments: int = 3, missing: int | None = None) -> None:
    """Fragments of a 4 m x 3 m room (overlapping x slabs, each in its own frame), gt.log and gt_overlap.log.

    The gt.log lists every pair ``i < j`` (plus one with fragment ``missing`` when given);
    gt_overlap.log lists only pair ``(0, 1)``, with the ratio 0.4242.
    """
    rng = np.random.default_rng(seed)
    floor = np.column_stack([rng.uniform(0, 4, 6000), rng.uniform(0, 3, 6000), np.zeros(6000)])
    wall = np.column_stack([rng.uniform(0, 4, 3000), np.full(3000, 3.0), rng.uniform(0, 2.5, 3000)])
    side = np.column_stack([np.zeros(2000), rng.uniform(0, 3, 2000), rng.uniform(0, 2.5, 2000)])
    world = np.concatenate([floor, wall, side])
    poses = [_pose(rng) for _ in range(fragments)]
    for k, pose in enumerate(poses):
        inside = world[(world[:, 0] >= k * 1.0) & (world[:, 0] < k * 1.0 + 2.0)]
        write_point_cloud(scene / f"cloud_bin_{k}.ply", ((inside - pose[:3, 3]) @ pose[:3, :3]).astype(np.float32))
    pairs = [(i, j) for j in range(fragments) for i in range(j)]
    blocks = [_log_block(i, j, fragments, np.linalg.inv(poses[i]) @ poses[j]) for i, j in pairs]
    if missing is not None:
        blocks.append(_log_block(0, missing, missing + 1, np.eye(4)))
    log_folder.mkdir(parents=True, exist_ok=True)
    (log_folder / "gt.log").write_text("".join(blocks))
    (log_folder / "gt_overlap.log").write_text("0,1,0.4242\n")


def _aligned_share(pair: PairSample) -> float:
    """Share of source points within 3.75 cm of the target after the ground truth."""
    gt = pair.gt_transform.astype(np.float64)
    moved = pair.src_xyz.astype(np.float64) @ gt[:3, :3].T + gt[:3, 3]
    return float(np.mean(cKDTree(pair.tgt_xyz).query(moved)[0] < 0.0375))


def test_a_scene_folder_gives_metric_pairs_with_overlaps(tmp_path):
    scene = tmp_path / "room"
    _write_scene(scene, scene, seed=0, missing=7)

    pairs = threedmatch_pairs(root=str(scene), dense_points=None)

    assert len(pairs) == 3  # the pair with the missing cloud_bin_7 is skipped, no demo pair
    assert [(p.meta["src_fragment"], p.meta["tgt_fragment"]) for p in pairs] == [
        ("cloud_bin_1", "cloud_bin_0"),
        ("cloud_bin_2", "cloud_bin_0"),
        ("cloud_bin_2", "cloud_bin_1"),
    ]
    assert all(p.meta["source"] == "3dmatch" and p.meta["scene"] == "room" for p in pairs)
    assert pairs[0].meta["overlap"] == 0.4242  # from gt_overlap.log
    for pair in pairs[1:]:  # measured
        assert 0.0 <= pair.meta["overlap"] <= 1.0
        assert pair.meta["overlap"] == pytest.approx(_aligned_share(pair), abs=0.02)
    assert pairs[2].meta["overlap"] > 0.3 and pairs[1].meta["overlap"] < 0.05  # slabs 1-3 overlap 2-3
    assert len(pairs[0].src_xyz) > 4000 and "scale" not in pairs[0].meta  # every point, in metres
    assert _aligned_share(pairs[2]) > 0.3


def test_a_folder_of_scenes_reads_every_scene_with_fragments_and_a_gt_log(tmp_path):
    _write_scene(tmp_path / "kitchen", tmp_path / "kitchen", seed=1, fragments=2)
    _write_scene(tmp_path / "office", tmp_path / "office-evaluation", seed=2, fragments=2)
    _write_scene(tmp_path / "unlabelled", tmp_path / "elsewhere", seed=3, fragments=2)
    (tmp_path / "notes").mkdir()

    pairs = threedmatch_pairs(root=str(tmp_path))

    assert [p.meta["scene"] for p in pairs] == ["kitchen", "office"]
    assert all(p.meta["overlap"] == 0.4242 for p in pairs)
    assert len(threedmatch_pairs(root=str(tmp_path), pairs=1)) == 1
    with pytest.raises(FileNotFoundError, match="not a 3DMatch scene"):
        threedmatch_pairs(root=str(tmp_path / "notes"))


@pytest.mark.shared_data
def test_the_default_3dmatch_pairs_are_in_metres(shared_data):
    pairs = threedmatch_pairs()

    assert [p.meta["dataset"] for p in pairs] == ["threedmatch", "geotransformer_demo"]
    assert all(p.meta["source"] == "3dmatch" for p in pairs)
    assert pairs[0].meta["overlap"] == pytest.approx(0.5422)  # gt_overlap.log
    assert pairs[1].meta["overlap"] == pytest.approx(0.40, abs=0.02)  # measured
    assert len(pairs[0].src_xyz) == 30000 and len(pairs[1].src_xyz) == 15_953  # the random cap
    rotation = pairs[1].gt_transform[:3, :3].astype(np.float64)
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-6)
    for pair in pairs:  # fewer neighbours within 3.75 cm in the capped clouds
        assert pair.meta["overlap"] >= _aligned_share(pair) > 0.85 * pair.meta["overlap"]


# ----------------------------------------------------------------------------- reports


def _record(pair, method, err_r, err_t, *, confident=False, bbox=1.0, overlap=None, source=None, gt=None):
    """A hand-made benchmark record."""
    meta = {key: value for key, value in (("overlap", overlap), ("source", source)) if value is not None}
    return {
        "pair": pair,
        "method": method,
        "seconds": 0.5,
        "err_r_deg": err_r,
        "err_t_l1": err_t,
        "err_t_l2": err_t,
        "err_pw_l1": err_t,
        "err_pw_l2": err_t,
        "diameter": 1.0,
        "bbox_diagonal": bbox,
        "confident": confident,
        "fitness": 0.5,
        "transform": np.eye(4).tolist(),
        "gt_transform": (np.eye(4) if gt is None else gt).tolist(),
        "meta": meta,
        "info": {},
    }


def test_registration_recall_needs_both_thresholds():
    records = [_record(0, "a", 1.0, 0.05), _record(1, "a", 10.0, 0.2), _record(2, "a", 14.9, 0.3)]
    records += [_record(3, "a", 20.0, 0.01), _record(0, "b", 1.0, 0.31)]

    summary = summarize_records(records)

    assert summary["a"][recall_key(15.0, 0.3)] == 0.75
    assert summary["a"][recall_key(5.0, 0.1)] == 0.25
    assert summary["b"][recall_key(15.0, 0.3)] == 0.0
    assert summary["a"]["err_r_deg_median"] == pytest.approx(12.45)
    assert summary["a"]["err_r_deg_registered_mean"] == pytest.approx((1.0 + 10.0 + 14.9) / 3)
    assert summary["a"]["err_t_l2_registered_mean"] == pytest.approx((0.05 + 0.2 + 0.3) / 3)
    assert np.isnan(summary["b"]["err_t_l2_registered_mean"])


def test_the_identity_baseline_is_the_ground_truth_motion():
    gt = np.eye(4)
    gt[:3, :3] = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    gt[:3, 3] = [0.3, 0.4, 0.0]
    records = [_record(0, "a", 1.0, 0.0, gt=gt), _record(0, "b", 1.0, 0.0, gt=gt)]

    (identity,) = identity_records(records)

    assert identity["method"] == IDENTITY
    assert identity["err_r_deg"] == pytest.approx(30.0) and identity["err_t_l2"] == pytest.approx(0.5)


def test_overlap_bins_and_the_per_bin_tables():
    assert [overlap_bin(v) for v in (0.1, 0.2, 0.35, 0.5, 0.8, 0.81)] == [
        "< 0.2",
        "[0.2, 0.3)",
        "[0.3, 0.5)",
        "[0.5, 0.8]",
        "[0.5, 0.8]",
        "> 0.8",
    ]
    records = [_record(0, "a", 1.0, 0.01, overlap=0.25), _record(1, "a", 30.0, 1.0, overlap=0.7)]
    records += [_record(2, "a", 1.0, 0.01, overlap=0.75)]

    lines = recall_sections(records, "m")

    assert lines[0].startswith("## Registration recall (RRE <= 15 deg and RTE <= 0.3 m")
    assert [line for line in lines if line.startswith("### ")] == [
        "### Overlap [0.2, 0.3) (1 pairs)",
        "### Overlap [0.5, 0.8] (2 pairs)",
    ]
    high = lines.index("### Overlap [0.5, 0.8] (2 pairs)")
    assert lines[high + 4].startswith("| a | 2 | 0.500 |")
    assert any(line.startswith(f"| {IDENTITY} | 3 |") for line in lines)
    assert not any(line.startswith("### ") for line in recall_sections([_record(0, "a", 1.0, 0.0)], "m"))


def test_the_confidence_flag_is_scored_against_correct_registrations():
    records = [
        _record(0, "a", 1.0, 0.01, confident=True),  # TP
        _record(1, "a", 5.0, 0.01, confident=True),  # FP: rotation off by more than 2 deg
        _record(2, "a", 1.0, 0.03, confident=False, bbox=2.0),  # FN: 3 cm <= 2 % of 2 m
        _record(3, "a", 1.0, 0.03, confident=False),  # TN: 3 cm > 2 % of 1 m
        _record(4, "a", 1.0, 0.01, confident=True),  # TP
    ]

    assert [is_correct(record) for record in records] == [True, False, True, False, True]
    counts = confusion(records)
    assert {key: counts[key] for key in ("tp", "fp", "fn", "tn")} == {"tp": 2, "fp": 1, "fn": 1, "tn": 1}
    assert counts["precision"] == pytest.approx(2 / 3) and counts["recall"] == pytest.approx(2 / 3)
    assert np.isnan(confusion(records[3:4])["precision"])
    lines = confidence_lines(records, "fragments")
    assert (
        "| a | 5 | 2 | 1 | 1 | 1 | 0.667 | 0.667 |" in lines and "| all | 5 | 2 | 1 | 1 | 1 | 0.667 | 0.667 |" in lines
    )
    assert not any(line.startswith("### Source") for line in lines)
    with pytest.raises(ValueError, match="no 'confident' flag"):
        confidence_lines([{key: v for key, v in records[0].items() if key != "confident"}], "fragments")


def test_the_table_leads_with_recall_for_metric_pairs(tmp_path):
    records = [_record(0, "a", 1.0, 0.01, overlap=0.6, confident=True), _record(1, "a", 40.0, 2.0, overlap=0.25)]

    metric = write_results(records, tmp_path / "metric", settings={"benchmark": {"name": "fragments"}})
    table = metric["table"].read_text()
    assert table.startswith("# Benchmark `fragments`: 2 pairs x 1 methods")
    assert "errors and thresholds in metres" in table
    assert table.index("## Registration recall") < table.index("## Confidence flag") < table.index("## Mean over")
    assert "recall (RRE <= 15 deg, RTE <= 0.3 m)" in table
    summary = json.loads(metric["json"].read_text())["summary"]["a"]
    assert summary[recall_key(15.0, 0.3)] == 0.5

    scaled = write_results(records, tmp_path / "scaled", settings={"benchmark": {"name": "3dmatch", "half_extent": 5}})
    table = scaled["table"].read_text()
    assert table.index("## Mean over") < table.index("## Registration recall")
    assert "RTE <= 0.3 pair units" in table


def test_confidence_pools_several_results_files(tmp_path, capsys):
    fragments = [_record(0, "a", 1.0, 0.01, confident=True, source="fragments")]
    shapes = [_record(0, "a", 1.0, 0.01, confident=False), _record(1, "a", 9.0, 0.01, confident=True)]
    paths = [
        write_results(fragments, tmp_path / "fragments", settings={"benchmark": {"name": "fragments"}})["json"],
        write_results(shapes, tmp_path / "human", settings={"benchmark": {"name": "human"}})["json"],
    ]

    pooled = pooled_records(paths)

    assert [record["meta"]["source"] for record in pooled] == ["fragments", "human", "human"]
    assert len({record["pair"] for record in pooled}) == 3
    lines = confidence_lines(pooled, "pairs")
    assert "| all | 3 | 1 | 1 | 1 | 0 | 0.500 | 0.500 |" in lines
    assert "### Source `fragments`" in lines and "### Source `human`" in lines
    assert bench_confidence.main([str(path) for path in paths]) == 0
    assert "### Source `human`" in capsys.readouterr().out


def test_run_benchmark_records_the_confidence_flag(monkeypatch):
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, (200, 3)).astype(np.float32)
    pair = PairSample(src_xyz=points, tgt_xyz=points * [2.0, 1.0, 1.0], gt_transform=np.eye(4, dtype=np.float32))
    seen = []

    def fake_quality(src, tgt, transform):
        seen.append(transform)
        return {"fitness": 0.7, "inlier_rmse": 0.01, "fitness_threshold": 0.05, "confident": True}

    def identity(src, tgt, src_normals=None, tgt_normals=None):
        return MethodResult(transform=np.eye(4), seconds=0.0)

    monkeypatch.setattr(benchmark_module, "quality", fake_quality)
    (record,) = run_benchmark([pair], {"identity": identity}, progress=False)

    assert record["confident"] is True and record["fitness"] == 0.7
    np.testing.assert_array_equal(seen[0], np.eye(4))
    expected = np.linalg.norm(pair.tgt_xyz.max(axis=0) - pair.tgt_xyz.min(axis=0))
    assert record["bbox_diagonal"] == pytest.approx(expected)
