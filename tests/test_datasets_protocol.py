"""Pair generation: procedural shapes, the paper's view protocol, RPM-Net's crop protocol."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from linereg.datasets import build_dataset
from linereg.datasets.procedural import ProceduralShapes, procedural_shape
from linereg.datasets.protocol import (
    CropProtocol,
    Shape,
    ShapeViews,
    ViewProtocol,
    build_protocol,
)
from linereg.datasets.shape_pairs import ShapePairDataset
from linereg.pointcloud import scale_transform


def _apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``R p + t`` in float64."""
    transform = np.asarray(transform, dtype=np.float64)
    return points @ transform[:3, :3].T + transform[:3, 3]


def _surface_in_target_frame(mesh: trimesh.Trimesh, pair, count: int = 60000) -> np.ndarray:
    """Dense samples of the shape surface mapped like the target: ``T((x - c) s)``."""
    surface, _ = trimesh.sample.sample_surface(mesh, count, seed=0)
    scaled = (surface - np.asarray(pair.meta["center"])) * pair.meta["scale"]
    return _apply(pair.gt_transform, scaled)


@pytest.fixture(scope="module")
def shapes() -> ProceduralShapes:
    return ProceduralShapes(3, seed=5)


@pytest.mark.parametrize("preset", ["airplane", "human"])
def test_gt_maps_source_onto_target_surface(shapes, preset):
    dataset = ShapePairDataset(shapes, build_protocol(preset), seed=1)
    mesh = shapes.load(0).mesh
    for index in (0, 7):
        pair = dataset[index]
        surface = cKDTree(_surface_in_target_frame(mesh, pair))
        source_error, _ = surface.query(_apply(pair.gt_transform, pair.src_xyz))
        target_error, _ = surface.query(pair.tgt_xyz)
        assert np.median(source_error) < 0.01
        assert np.percentile(source_error, 99) < 0.03
        assert np.percentile(target_error, 99) < 0.03
        moved = _apply(pair.gt_transform, pair.src_xyz)
        assert np.median(cKDTree(pair.tgt_xyz).query(moved)[0]) < 0.06


def test_pairs_follow_the_paper_format(shapes):
    dataset = ShapePairDataset(shapes, build_protocol("airplane"), seed=0)
    assert len(dataset) == 3 * 18
    pair = dataset[3]
    for cloud in (pair.src_xyz, pair.tgt_xyz, pair.src_normals, pair.tgt_normals):
        assert cloud.shape == (1024, 3) and cloud.dtype == np.float32
    assert pair.gt_transform.shape == (4, 4) and pair.gt_transform.dtype == np.float32
    assert np.abs(pair.src_xyz).max() <= 1.0 + 1e-5
    np.testing.assert_allclose(np.linalg.norm(pair.src_normals, axis=1), 1.0, atol=1e-4)
    rotation = pair.gt_transform[:3, :3].astype(np.float64)
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-5)
    assert np.all(np.abs(pair.gt_transform[:3, 3]) <= 0.2 + 1e-6)
    assert pair.meta["view"] == 3 and pair.meta["shape"] == "procedural_train_00000"
    assert len(np.unique(pair.src_xyz, axis=0)) == 1024


def test_source_is_a_partial_view(shapes):
    dataset = ShapePairDataset(shapes, build_protocol("human"), seed=0)
    pair = dataset[0]
    moved = _apply(pair.gt_transform, pair.src_xyz)
    covered, _ = cKDTree(moved).query(pair.tgt_xyz)
    assert (covered < 0.05).mean() < 0.7, "the whole target should extend beyond the view"
    assert (covered < 0.05).mean() > 0.15


def test_estimated_normals_face_the_camera(shapes):
    protocol = build_protocol("airplane")
    views = ShapeViews(shapes.load(1))
    eye, _ = protocol.camera_pose(views, 2)
    pair = ShapePairDataset(shapes, protocol, seed=0)[18 + 2]
    # Undo the joint scaling to compare with the camera position in shape coordinates.
    source = pair.src_xyz / pair.meta["scale"] + np.asarray(pair.meta["center"])
    towards_camera = np.sum(pair.src_normals * (eye - source), axis=1)
    assert (towards_camera > 0).mean() > 0.99


def test_pairs_are_deterministic_by_seed(shapes):
    first = ShapePairDataset(shapes, build_protocol("airplane"), seed=3)
    again = ShapePairDataset(ProceduralShapes(3, seed=5), build_protocol("airplane"), seed=3)
    other = ShapePairDataset(shapes, build_protocol("airplane"), seed=4)
    a, b, c = first[20], again[20], other[20]
    np.testing.assert_array_equal(a.src_xyz, b.src_xyz)
    np.testing.assert_array_equal(a.tgt_xyz, b.tgt_xyz)
    np.testing.assert_array_equal(a.gt_transform, b.gt_transform)
    assert not np.allclose(a.gt_transform, c.gt_transform)
    assert not np.array_equal(first[0].gt_transform, first[1].gt_transform)


def test_splits_use_disjoint_shapes_and_poses():
    train = build_dataset({"name": "procedural", "num_shapes": 2, "split": "train"})
    test = build_dataset({"name": "procedural", "num_shapes": 2, "split": "test"})
    assert not np.allclose(train[0].gt_transform, test[0].gt_transform)
    train_mesh = train.shapes.load(0).mesh
    test_mesh = test.shapes.load(0).mesh
    assert len(train_mesh.vertices) != len(test_mesh.vertices) or not np.allclose(
        train_mesh.vertices, test_mesh.vertices
    )


def test_procedural_shapes_are_connected_asymmetric_and_unit_sized():
    rng = np.random.default_rng(0)
    for _ in range(3):
        mesh = procedural_shape(rng)
        assert np.linalg.norm(mesh.vertices, axis=1).max() == pytest.approx(1.0)
        points, _ = trimesh.sample.sample_surface(mesh, 4000, seed=1)
        tree = cKDTree(points)
        # No rotation in a coarse grid maps the shape onto itself (registration is well posed).
        for axis in np.eye(3):
            for angle in (np.pi / 2, np.pi):
                rotation = trimesh.transformations.rotation_matrix(angle, axis)[:3, :3]
                distance, _ = tree.query(points @ rotation.T)
                assert np.mean(distance) > 0.03


def test_point_cloud_shapes_use_hidden_point_removal():
    mesh = procedural_shape(np.random.default_rng(3))
    points, faces = trimesh.sample.sample_surface(mesh, 8000, seed=2)
    shape = Shape("cloud", points=points.astype(np.float32), normals=mesh.face_normals[faces])
    views = ShapeViews(shape)
    protocol = build_protocol("airplane")
    eye, up = protocol.camera_pose(views, 0)
    visible, normals = views.render(eye, up, protocol.image_size)
    assert 0.05 * len(points) < len(visible) < 0.5 * len(points)
    assert normals is not None and normals.shape == visible.shape
    # Hidden point removal keeps what the ray-cast camera sees on the mesh itself.
    rendered, _ = ShapeViews(Shape("mesh", mesh=mesh)).render(eye, up, protocol.image_size)
    distance, _ = cKDTree(rendered).query(visible)
    assert np.median(distance) < 0.01


def test_crop_protocol_matches_rpmnet():
    shapes = ProceduralShapes(2, seed=1)
    protocol = build_protocol({"name": "rpmnet_crop", "noise_std": 0.0})
    assert isinstance(protocol, CropProtocol)
    pair = ShapePairDataset(shapes, protocol, seed=0)[1]
    assert pair.src_xyz.shape == pair.tgt_xyz.shape == (717, 3)
    moved = _apply(pair.gt_transform, pair.src_xyz)
    distance, _ = cKDTree(pair.tgt_xyz).query(moved)
    assert 0.3 < (distance < 0.03).mean() < 0.95
    assert np.abs(np.linalg.inv(pair.gt_transform)[:3, 3]).max() <= 0.5 + 1e-5


def test_scale_transform_matches_scaled_clouds():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(50, 3))
    transform = trimesh.transformations.random_rotation_matrix(rng.random(3))
    transform[:3, 3] = [0.3, -1.0, 2.0]
    center, scale = np.array([0.5, 0.1, -0.2]), 2.5
    scaled = scale_transform(transform, center, scale)
    np.testing.assert_allclose(_apply(scaled, (points - center) * scale), (_apply(transform, points) - center) * scale)


def test_protocol_errors_name_the_problem():
    with pytest.raises(ValueError, match="unknown protocol 'plane'"):
        build_protocol("plane")
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['views'\]"):
        build_protocol({"name": "airplane", "views": 3})
    with pytest.raises(ValueError, match="target must be"):
        ViewProtocol(target="mesh")
    with pytest.raises(ValueError, match="mesh is empty"):
        Shape("empty", mesh=trimesh.Trimesh())
    with pytest.raises(ValueError, match="exactly one of mesh and points"):
        Shape("nothing")
