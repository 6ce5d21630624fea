"""Traps for ``confident``: clutter, units, mirror images and shapes with no unique pose; ``scale=True``;
the register command's warnings and scale (registration/trust.py, registration/similarity.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import linereg
from linereg.io import write_point_cloud, write_transform
from linereg.knn import NearestNeighbors
from linereg.registration import trust
from linereg.registration.poses import rotation_gap_deg
from linereg.train.register import RegisterError, register_files
from tests.conftest import compose_register


def bumpy(count: int, seed: int) -> np.ndarray:
    """Independent samplings of one bumpy ellipsoid with no symmetry (a unique pose)."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(count, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    bump = (
        1.0 + 0.25 * np.sin(3.0 * x[:, 0]) * np.cos(2.0 * x[:, 1]) + 0.2 * np.sin(2.0 * x[:, 1] + 3.0 * x[:, 2] + 0.7)
    )
    return x * bump[:, None] * np.array([1.4, 1.0, 0.7])


TRUTH = np.array(
    [[0.9396926, -0.3420201, 0.0, 0.3], [0.3420201, 0.9396926, 0.0, -0.2], [0.0, 0.0, 1.0, 0.1], [0.0, 0.0, 0.0, 1.0]]
)


def moved(points: np.ndarray, transform: np.ndarray) -> np.ndarray:
    return points @ transform[:3, :3].T + transform[:3, 3]


def rotation_error(result, truth: np.ndarray) -> float:
    rotation = result.transformation[:3, :3] / result.scale
    scale = np.cbrt(np.linalg.det(truth[:3, :3]))
    return float(rotation_gap_deg(rotation[None], truth[:3, :3] / scale)[0])


def test_chance_fitness_matches_its_naive_twin():
    """The quantile of the shares within the radius at the placements, written out point by point."""
    rng = np.random.default_rng(0)
    source, target = bumpy(300, 1), bumpy(2000, 2)
    index = NearestNeighbors(target)
    radius = 0.1
    found = trust.chance_fitness(source, index, radius, seed=3)
    draw = np.random.default_rng(3)
    rotations = trust.random_rotations(trust.CHANCE_PLACEMENTS, draw)
    anchors = target[draw.integers(len(target), size=trust.CHANCE_PLACEMENTS)]
    shares = []
    for rotation, anchor in zip(rotations, anchors, strict=True):
        placed = (source - source.mean(axis=0)) @ rotation.T + anchor
        shares.append(np.mean([np.min(np.linalg.norm(target - p, axis=1)) <= radius for p in placed]))
    assert found == pytest.approx(np.quantile(shares, trust.CHANCE_QUANTILE))
    assert rng is not None and np.allclose(rotations @ rotations.transpose(0, 2, 1), np.eye(3), atol=1e-9)


def test_a_plane_leaves_three_motions_free_and_a_bumpy_shape_none():
    """Two independent samplings of each (an exact copy fits only at its own points)."""
    plane, other = _plane(3000, 0), _plane(800, 1) * [0.5, 0.5, 1.0] + [0.25, 0.25, 0.0]
    index = NearestNeighbors(plane)
    free = trust.free_motions(other, other, index, trust.spacing_of(plane))
    assert sorted(motion.kind for motion in free) == ["rotation", "translation", "translation"]
    rotation = next(motion for motion in free if motion.kind == "rotation")
    assert abs(rotation.axis[2]) > 0.99  # about the plane's normal
    shape, other = bumpy(3000, 0), bumpy(800, 1)
    index = NearestNeighbors(shape)
    assert trust.free_motions(other, other, index, trust.spacing_of(shape)) == []


def test_chance_decides_with_a_margin_and_either_a_factor_or_the_misses():
    assert trust.beats_chance(0.4, 0.05)  # a partial overlap: far above chance
    assert not trust.beats_chance(0.36, 0.22)  # a wrong pose in clutter
    assert not trust.beats_chance(1.0, 1.0)  # a tiny source inside a target in larger units
    assert trust.beats_chance(1.0, 0.52)  # an exact fit of a volume-like cloud


@pytest.mark.parametrize("share", [0.5, 0.8])
def test_clutter_neither_fools_the_check_nor_the_solver(share):
    """The target plus uniform clutter in its bounding box: at 50 % the right answer, trusted; at
    80 % of a sparse synthetic target (12 000 points) right and trusted, or not trusted."""
    rng = np.random.default_rng(1)
    source, target = bumpy(8000, 1), moved(bumpy(12000, 2), TRUTH)
    clutter = rng.uniform(target.min(axis=0), target.max(axis=0), (int(len(target) * share / (1 - share)), 3))
    result = linereg.register(source, np.concatenate([target, clutter]))
    right = rotation_error(result, TRUTH) < 1.0
    assert right and result.confident if share == 0.5 else right or not result.confident
    if share == 0.5:
        assert 0.2 < result.info["clutter"] <= share  # the clutter the solver did not see


def test_a_wrong_pose_in_clutter_is_no_better_than_chance():
    rng = np.random.default_rng(2)
    source, target = bumpy(3000, 1), bumpy(4000, 2)
    clutter = rng.uniform(target.min(axis=0), target.max(axis=0), (9 * len(target), 3))
    turned = TRUTH.copy()
    turned[:3, 3] = 0.0
    found = linereg.registration.api.quality(source, np.concatenate([target, clutter]), turned, on_surface=None)
    assert not found["confident"] and any("chance" in note for note in found["warnings"])


@pytest.mark.parametrize("factor", [1000.0, 0.001, 2.0, 0.5])
def test_other_units_are_caught_rigidly_and_solved_with_scale(factor):
    source, target = bumpy(3000, 1), factor * moved(bumpy(4000, 2), TRUTH)
    rigid = linereg.register(source, target)
    assert not rigid.confident and rigid.scale == 1.0
    assert any("scale=true" in note for note in rigid.info["warnings"])
    similar = linereg.register(source, target, scale=True)
    truth = np.diag([factor, factor, factor, 1.0]) @ TRUTH
    assert similar.confident and rotation_error(similar, truth) < 0.5
    assert abs(similar.scale / factor - 1.0) < 0.01
    assert np.cbrt(np.linalg.det(similar.transformation[:3, :3])) == pytest.approx(similar.scale)


def test_a_free_scale_is_fixed_by_the_point_spacings_only_within_its_free_range():
    """A fit that leaves its scale free takes the spacings' ratio only where that ratio lies within the
    free range and the rigid answer there is trusted; otherwise the fit stands."""
    from linereg.knn import NearestNeighbors
    from linereg.registration.api import _Judge, _scale_by_spacing
    from linereg.registration.methods import MethodResult

    source, target = bumpy(3000, 1), 2.0 * moved(bumpy(4000, 2), TRUTH)
    judge = _Judge(None, None, NearestNeighbors(target))
    fitted = (MethodResult(np.eye(4), 0.0, {}), 1.95, {"confident": False})
    truth = np.diag([2.0, 2.0, 2.0, 1.0]) @ TRUTH
    rigid = MethodResult(truth @ np.diag([0.5, 0.5, 0.5, 1.0]), 0.0, {})  # maps the source x2 onto the target
    held, factor, found = _scale_by_spacing(fitted, 2.0, rigid, source, target, judge)
    assert factor == 2.0 and found.confident and held.info["scale_from"] == "point spacings"
    assert np.allclose(held.transform, truth)
    assert _scale_by_spacing(fitted, 2.1, rigid, source, target, judge) is fitted  # outside the free range
    wrong = MethodResult(np.linalg.inv(TRUTH), 0.0, {})
    assert _scale_by_spacing(fitted, 2.0, wrong, source, target, judge) is fitted  # not trusted there


def test_a_mirror_image_is_not_trusted():
    source, target = bumpy(3000, 1), bumpy(4000, 2) * [-1.0, 1.0, 1.0]
    result = linereg.register(source, target)
    assert not result.confident and result.info["warnings"]


def _sphere(count: int, seed: int) -> np.ndarray:
    points = np.random.default_rng(seed).normal(size=(count, 3))
    return points / np.linalg.norm(points, axis=1, keepdims=True)


def _box(count: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    points = rng.uniform(-0.5, 0.5, (count, 3))
    axis = rng.integers(3, size=count)
    points[np.arange(count), axis] = np.sign(points[np.arange(count), axis]) * 0.5
    return points * [1.0, 1.5, 2.0]


def _plane(count: int, seed: int) -> np.ndarray:
    return np.column_stack([np.random.default_rng(seed).uniform(0, 1, (count, 2)), np.zeros(count)])


@pytest.mark.parametrize(
    "shape, phrase", [(_plane, "planar"), (_sphere, "not unique"), (_box, "not unique")], ids=["plane", "sphere", "box"]
)
def test_a_shape_with_no_unique_pose_is_never_confident(shape, phrase):
    """Any answer on a plane, a sphere or a symmetric box is one of many: not trusted, and said why."""
    source, target = shape(3000, 1), shape(3000, 2)
    for transform in (np.eye(4), TRUTH):
        found = linereg.registration.api.quality(moved(source, transform), target, np.linalg.inv(transform))
        assert not found["confident"]
        assert any(phrase in note for note in found["warnings"]), found["warnings"]


def test_the_command_solves_a_scale_and_reports_its_error(tmp_path, capsys):
    source, target = bumpy(2500, 1), 1000.0 * moved(bumpy(3000, 2), TRUTH)
    write_point_cloud(tmp_path / "a.ply", source)
    write_point_cloud(tmp_path / "b.ply", target)
    write_transform(tmp_path / "gt.txt", np.diag([1000.0, 1000.0, 1000.0, 1.0]) @ TRUTH)
    rigid = compose_register(source=tmp_path / "a.ply", target=tmp_path / "b.ply")
    result, report = register_files(rigid, tmp_path / "rigid")
    assert not result.confident and any("scale=true" in note for note in report["warnings"])
    assert "scale=true" in capsys.readouterr().err
    with pytest.raises(RegisterError, match="gt="):
        register_files(
            compose_register(source=tmp_path / "a.ply", target=tmp_path / "b.ply", gt=tmp_path / "gt.txt"),
            tmp_path / "x",
        )
    cfg = compose_register(source=tmp_path / "a.ply", target=tmp_path / "b.ply", gt=tmp_path / "gt.txt", scale="true")
    result, _ = register_files(cfg, tmp_path / "run")
    saved = json.loads((tmp_path / "run" / "result.json").read_text())
    assert saved["confident"] and saved["scale"] == pytest.approx(1000.0, rel=0.01)
    assert saved["metrics"]["err_r_deg"] < 1.0 and abs(saved["metrics"]["scale_error"]) < 0.01


def test_real_scans_in_clutter_and_in_millimetres(shared_data):
    """The Bunny's range scans (bun045 onto bun000, the lab's alignment): right and trusted in 80 %
    clutter, and in millimetres with ``scale=True``; not trusted in millimetres without it."""
    from linereg.datasets.formats import read_conf
    from linereg.io import read_point_cloud

    folder = shared_data / "scans/stanford_bunny_range"
    if not folder.is_dir():
        pytest.skip(f"{folder} not found")
    poses = read_conf(folder / "bun.conf")
    truth = np.linalg.inv(poses["bun000.ply"]) @ poses["bun045.ply"]
    source, target = read_point_cloud(folder / "bun045.ply").xyz, read_point_cloud(folder / "bun000.ply").xyz
    rng = np.random.default_rng(0)
    clutter = rng.uniform(target.min(axis=0), target.max(axis=0), (4 * len(target), 3))
    cluttered = linereg.register(source, np.concatenate([target, clutter]))
    assert cluttered.confident and rotation_error(cluttered, truth) < 1.0
    millimetres = linereg.register(source, 1000.0 * target, scale=True)
    assert millimetres.confident and rotation_error(millimetres, truth) < 0.5
    assert abs(millimetres.scale / 1000.0 - 1.0) < 0.01


def test_a_room_pair_in_other_units_takes_its_scale_from_the_point_spacings(shared_data):
    """The GeoTransformer 3DMatch demo pair, its target x2: the similarity fit leaves the scale free
    by 3 % (planes slide); the spacings' ratio fixes it, and the answer is trusted."""
    folder = shared_data / "3dmatch/geotransformer_demo/demo"
    if not folder.is_dir():
        pytest.skip(f"{folder} not found")
    source, target, truth = (np.load(folder / f"{name}.npy") for name in ("src", "ref", "gt"))
    result = linereg.register(source, 2.0 * target, scale=True)
    assert result.confident and result.info["scale_from"] == "point spacings"
    assert abs(result.scale / 2.0 - 1.0) < 0.01 and rotation_error(result, truth) < 2.0
