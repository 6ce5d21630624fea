"""``linereg.register_scans`` and ``linereg-register scans=<folder>``: a turntable with known poses."""

from __future__ import annotations

import csv
import os
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import linereg
from linereg.datasets.procedural import procedural_shape
from linereg.io import read_point_cloud, write_point_cloud, write_transform
from linereg.paths import REPO_ROOT
from linereg.pointcloud import hidden_point_removal
from linereg.registration.multiway import Edge, MultiwayOptions, place_scans
from linereg.train.register_scans import pose_errors, read_gt_poses
from tests.conftest import compose_register

TURN_DEG = 45.0
FAST = {"num_points": 512, "progress": False}
"""Fewer solver points than the default: the scans hold about 600 points."""


def turntable(count: int, seed: int = 0) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """``count`` views of one shape turned by :data:`TURN_DEG` each on a turntable (the points the camera
    sees, in the turned frame) and each view's ``(4, 4)`` pose in the first view's frame."""
    shape = np.asarray(procedural_shape(np.random.default_rng(seed)).sample(2000, seed=seed), dtype=np.float64)
    shape = (shape - shape.mean(axis=0)) / np.abs(shape).max()
    scans, poses = [], []
    for k in range(count):
        turn = Rotation.from_euler("z", k * TURN_DEG, degrees=True).as_matrix()
        turned = shape @ turn.T
        scans.append(turned[hidden_point_removal(turned, np.array([4.0, 0.0, 1.0]))])
        pose = np.eye(4)
        pose[:3, :3] = turn.T
        poses.append(pose)
    return scans, poses


@pytest.fixture(scope="module")
def table():
    """Five turntable views and a view of another shape, registered in sequence mode."""
    scans, poses = turntable(5)
    stranger = turntable(1, seed=11)[0][0] + np.array([0.3, 0.0, 0.0])
    result = linereg.register_scans([*scans, stranger], mode="sequence", **FAST)
    return [*scans, stranger], poses, result


def assert_placed_exactly(result, poses: list[np.ndarray]) -> None:
    for k, truth in enumerate(poses):
        assert result.placed[k], result.verdicts[k]
        rotation, translation = pose_errors(result.poses[k], truth)
        assert rotation < 0.5 and translation < 0.005, (k, rotation, translation)


def test_every_turntable_scan_is_placed_exactly(table):
    scans, poses, result = table
    assert_placed_exactly(result, poses)
    assert result.verdicts[0].startswith("first scan") and "placed by its edges to scan_0" in result.verdicts[1]
    odometry = [edge for edge in result.edges if edge.kind == "odometry"]
    assert [(edge.source, edge.target) for edge in odometry] == [(k, k + 1) for k in range(5)]
    assert all(edge.kept for edge in odometry[:4])
    assert result.merged.shape[1] == 3 and len(result.merged) > len(scans[0])


def test_a_scan_no_confident_edge_reaches_is_reported_and_never_placed(table):
    _, _, result = table
    assert not result.placed[5] and result.poses[5] is None
    assert result.verdicts[5] == "left out: no confident edge reaches it (registered against scan_4)"


def test_a_wrong_pair_is_dropped_by_the_graph(table):
    scans, poses, result = table
    wrong_turn = np.eye(4)
    wrong_turn[:3, :3] = Rotation.from_euler("z", 40.0, degrees=True).as_matrix()
    truth = np.linalg.inv(poses[3]) @ poses[0]
    wrong = Edge(0, 3, wrong_turn @ truth, 0.99, 0.001, True, 0.0, "loop closure")
    again = place_scans(scans, [*result.edges, wrong])
    assert not again.edges[-1].kept
    assert_placed_exactly(again, poses)
    assert "scan_0" not in again.verdicts[3]


def test_unordered_scans_are_placed_from_the_best_candidate_pairs():
    scans, poses = turntable(4, seed=2)
    order = [0, 2, 3, 1]
    result = linereg.register_scans(
        [scans[k] for k in order], mode="unordered", options=MultiwayOptions(candidates=2), **FAST
    )
    first = np.linalg.inv(poses[order[0]])
    assert_placed_exactly(result, [first @ poses[k] for k in order])
    assert {edge.kind for edge in result.edges} == {"candidate"}
    assert len(result.edges) < 6


def _quaternion_line(name: str, pose: np.ndarray) -> str:
    """A ``bmesh`` line of a ``.conf`` placing a scan point ``x`` at ``R(q)^T x + t``."""
    x, y, z, w = Rotation.from_matrix(pose[:3, :3].T).as_quat()
    return f"bmesh {name} {' '.join(map(str, pose[:3, 3]))} {x} {y} {z} {w}"


def test_ground_truth_from_a_conf_a_log_and_a_folder(tmp_path):
    _, poses = turntable(3)
    common = np.eye(4)
    common[:3, 3] = [0.5, -0.2, 0.1]
    placed = [common @ pose for pose in poses]
    files = [tmp_path / f"scan_{k}.ply" for k in range(3)]
    conf = tmp_path / "scans.conf"
    lines = [_quaternion_line(file.name, pose) for file, pose in zip(files, placed, strict=True)]
    conf.write_text("camera 0 0 0 0 0 0 1\n" + "\n".join(lines) + "\n")
    log = tmp_path / "trajectory.log"
    blocks = [f"{k} {k} 3\n" + "".join(" ".join(map(str, row)) + "\n" for row in pose) for k, pose in enumerate(placed)]
    log.write_text("".join(blocks))
    folder = tmp_path / "poses"
    for k, pose in enumerate(placed):
        write_transform(folder / f"pose_{k}.txt", pose)
    for source in (conf, log, folder):
        for found, pose in zip(read_gt_poses(source, files), poses, strict=True):
            np.testing.assert_allclose(found, pose, atol=1e-6)
    with pytest.raises(ValueError, match="3 poses for 2 scans"):
        read_gt_poses(folder, files[:2])
    with pytest.raises(ValueError, match="no pose for other"):
        read_gt_poses(conf, [*files, tmp_path / "other.ply"])


def _compose(**overrides):
    return compose_register(**{"progress": "false", **overrides})


def test_the_command_writes_its_outputs_in_natural_order_and_resumes(tmp_path, capsys):
    from linereg.train.register import _register_scans

    scans, poses = turntable(3)
    folder, truths = tmp_path / "scans", tmp_path / "truths"
    names = ["scan_1", "scan_2", "scan_10"]
    for name, scan, pose in zip(names, scans, poses, strict=True):
        write_point_cloud(folder / f"{name}.ply", scan)
        write_transform(truths / f"{name}.txt", pose)
    out = tmp_path / "run"
    cfg = _compose(scans=folder, gt=truths, num_points=512, **{"+multiway.loop_closures": 0})
    _register_scans(cfg, out)
    first = capsys.readouterr().out
    assert "3 of 3 scans placed; 2 edges (2 registered, 0 already in edges.csv)" in first
    (out / "merged.ply").unlink()
    _register_scans(cfg, out)
    assert "3 of 3 scans placed; 2 edges (0 registered, 2 already in edges.csv)" in capsys.readouterr().out
    lines = (out / "poses.txt").read_text().splitlines()
    assert [line.split()[0] for line in lines] == names
    for line, pose in zip(lines, poses, strict=True):
        np.testing.assert_allclose(np.array(line.split()[1:], dtype=float).reshape(4, 4), pose, atol=0.01)
    with open(out / "edges.csv", newline="") as stream:
        edges = list(csv.DictReader(stream))
    assert [(row["source"], row["target"], row["kept"]) for row in edges] == [
        ("scan_1", "scan_2", "true"),
        ("scan_2", "scan_10", "true"),
    ]
    with open(out / "scans.csv", newline="") as stream:
        assert all(float(row["err_r_deg"]) < 0.5 for row in csv.DictReader(stream))
    assert len(read_point_cloud(out / "merged.ply").xyz) > len(scans[0])


def _repo_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT), env.get("PYTHONPATH", "")])
    return env


def test_bad_input_ends_the_command_with_one_line(tmp_path):
    empty, one, two, corrupt = (tmp_path / name for name in ("empty", "one", "two", "corrupt"))
    empty.mkdir()
    scan = turntable(1)[0][0]
    for file in (one / "a.ply", two / "a.ply", two / "b.ply", corrupt / "a.ply"):
        write_point_cloud(file, scan)
    (corrupt / "b.ply").write_text("not a ply file")
    cases = {
        f"scans={empty}": "0 point-cloud file(s)",
        f"scans={one}": "1 point-cloud file(s)",
        f"scans={corrupt}": "b.ply",
        f"scans={two} gt={tmp_path / 'missing.conf'}": "no such file",
    }
    for arguments, message in cases.items():
        command = [sys.executable, "-m", "train.register", *arguments.split(), "progress=false"]
        done = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, env=_repo_env(), timeout=300)
        assert done.returncode == 2, done.stderr
        assert message in done.stderr and "Traceback" not in done.stderr and len(done.stderr.splitlines()) == 1
        assert not (tmp_path / "outputs").exists()


@pytest.mark.slow
@pytest.mark.shared_data
def test_the_stanford_bunny_scans_are_placed_within_half_a_degree_and_a_millimetre(shared_data):
    root = shared_data / "scans" / "stanford_bunny_range"
    files = sorted(root.glob("*.ply"))
    result = linereg.register_scans(files, mode="unordered", progress=False)
    truths = read_gt_poses(root / "bun.conf", files)
    for k, truth in enumerate(truths):
        assert result.placed[k], result.verdicts[k]
        rotation, translation = pose_errors(result.poses[k], truth)
        assert rotation < 0.5 and translation < 0.001, (files[k].name, rotation, translation)
