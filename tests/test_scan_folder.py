"""``dataset=scan_folder``: natural name order, neighbour and listed pairs, disjoint held-out parts,
poses read by the test split alone, and one-line errors for bad folders and keys."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np
import pytest

from linereg.datasets.scan_folder import ScanFolderPairs, held_out_parts, natural_key, neighbour_pairs
from linereg.datasets.splits import build_split
from linereg.io import write_point_cloud

ROOT = Path(__file__).resolve().parent.parent
CONFIG = {
    "name": "scan_folder",
    "num_points": 32,
    "dense_points": None,
    "splits": {
        "train": {"part": "train", "poses": None},
        "val": {"part": "val", "poses": None},
        "test": {"part": "test"},
    },
}


def write_scans(folder: Path, names: list[str], *, points: int = 60) -> Path:
    """Small random clouds ``<name>.ply`` in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for name in names:
        write_point_cloud(folder / f"{name}.ply", rng.standard_normal((points, 3)))
    return folder


def write_conf(path: Path, names: list[str]) -> None:
    """A Stanford ``.conf`` placing scan ``i`` at a translation of ``i`` along x."""
    lines = [f"bmesh {name}.ply {i} 0 0 0 0 0 1" for i, name in enumerate(names)]
    path.write_text("\n".join(lines) + "\n")


def test_scans_are_in_natural_name_order(tmp_path):
    names = ["scan_10", "scan_2", "scan_1", "Scan_3"]
    folder = write_scans(tmp_path / "scans", names)
    (folder / "notes.md").write_text("not a scan")
    dataset = ScanFolderPairs(folder, frame_gap=1, num_points=32, dense_points=None)
    assert [scan.stem for scan in dataset.scans] == ["scan_1", "scan_2", "Scan_3", "scan_10"]
    assert sorted(["b10", "b9", "a1"], key=natural_key) == ["a1", "b9", "b10"]
    assert [dataset.make_pair(i).meta["name"] for i in range(3)] == ["scan_1-scan_2", "scan_2-Scan_3", "Scan_3-scan_10"]


def test_neighbours_up_to_the_frame_gap_or_the_listed_pairs(tmp_path):
    assert neighbour_pairs(4, 2) == [(0, 1), (0, 2), (1, 2), (1, 3), (2, 3)]
    folder = write_scans(tmp_path / "scans", ["a", "b", "c"])
    (folder / "pairs.txt").write_text("# source target\nc.ply a\nb c  # a comment\n")
    dataset = ScanFolderPairs(folder, pairs_file="pairs.txt", num_points=32, dense_points=None)
    assert [scan.name for scan in dataset.scans] == ["a.ply", "b.ply", "c.ply"]  # pairs.txt is not a scan
    assert dataset.pairs == [(2, 0), (1, 2)]


@pytest.mark.parametrize("count", [4, 11, 40])
def test_held_out_parts_are_disjoint_and_cover_every_pair(count):
    parts = held_out_parts(count, 0.25, 0.2, seed=3)
    train, val, test = (set(parts[name]) for name in ("train", "val", "test"))
    assert train and val and test
    assert not train & val and not train & test and not val & test
    assert train | val | test == set(range(count))
    assert held_out_parts(count, 0.25, 0.0, seed=3)["test"] == held_out_parts(count, 0.25, 0.0, seed=3)["val"]


def test_splits_are_disjoint_and_only_the_test_split_reads_poses(tmp_path, monkeypatch):
    names = [f"s{i}" for i in range(8)]
    folder = write_scans(tmp_path / "scans", names)
    write_conf(folder / "poses.conf", names)
    config = {**CONFIG, "root": str(folder), "frame_gap": 2, "val_share": 0.25, "test_share": 0.25}
    config["poses"] = "poses.conf"
    read = []
    monkeypatch.setattr("linereg.datasets.scan_folder.read_conf", lambda path: read.append(path) or {})
    train, val = build_split(config, "train"), build_split(config, "val")
    assert not read and train[0].gt_transform is None and val[0].gt_transform is None
    assert not set(train.pairs) & set(val.pairs)
    monkeypatch.undo()
    test = build_split(config, "test")
    assert not set(test.pairs) & (set(train.pairs) | set(val.pairs))
    source, target = test.pairs[0]
    pair = test[0]
    expected = np.eye(4)
    expected[0, 3] = (source - target) * pair.meta["scale"]  # scan i sits at x = i; scaled into the cube
    np.testing.assert_allclose(pair.gt_transform, expected, atol=1e-5)


def test_copies_turn_the_source_and_keep_the_files_out_of_the_check(tmp_path):
    folder = write_scans(tmp_path / "scans", ["a", "b"])
    plain = ScanFolderPairs(folder, num_points=None, dense_points=None, half_extent=None)
    turned = ScanFolderPairs(
        folder, copies=3, source_motion_deg=30, num_points=None, dense_points=None, half_extent=None
    )
    assert len(turned) == 3 and "file" in plain[0].meta and "file" not in turned[0].meta
    first, second = np.sort(turned[0].src_xyz, axis=0), np.sort(turned[1].src_xyz, axis=0)
    assert not np.allclose(first, second)
    np.testing.assert_allclose(turned[0].tgt_xyz, plain[0].tgt_xyz)


def _train(arguments: list[str], monkeypatch, tmp_path) -> int:
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    monkeypatch.setattr(sys, "argv", ["linereg-train", *arguments])
    try:
        importlib.import_module("linereg.train.__main__").main()
    except SystemExit as exit:
        return int(exit.code or 0)
    return 0


@pytest.mark.parametrize(
    ("scans", "extra", "named"),
    [
        ([], [], "holds 0 scan(s)"),
        (["only"], [], "holds 1 scan(s)"),
        (["a", "b"], [], "cannot give 1 validation"),
        (["a", "b", "c"], ["+dataset.frame_gaps=2"], "frame_gaps"),
    ],
    ids=["empty folder", "one scan", "too few pairs", "unknown key"],
)
def test_bad_input_ends_in_one_line(scans, extra, named, tmp_path, monkeypatch, capsys):
    folder = write_scans(tmp_path / "scans", scans)
    (tmp_path / "work").mkdir()
    arguments = ["experiment=rpm_ours", "dataset=scan_folder", f"dataset.root={folder}", "trainer.device=cpu", *extra]
    assert _train(arguments, monkeypatch, tmp_path / "work") == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("linereg-train: error: ") and named in line and "Traceback" not in line
