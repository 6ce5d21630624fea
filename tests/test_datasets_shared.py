"""Dataset sources on the real shared data (skipped when ../shared/data is absent)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from linereg.datasets import build_dataset
from linereg.datasets.formats import read_depth_image, read_intrinsics
from linereg.datasets.rgbd import depth_to_points
from linereg.io import read_mesh

pytestmark = pytest.mark.shared_data

DENSE = {"num_points": None, "dense_points": None, "half_extent": None}


def _distances(pair, transform=None) -> np.ndarray:
    """Distance from each source point, moved by ``transform`` (default GT), to the target."""
    transform = np.asarray(pair.gt_transform if transform is None else transform, dtype=np.float64)
    moved = pair.src_xyz @ transform[:3, :3].T + transform[:3, 3]
    return cKDTree(pair.tgt_xyz).query(moved)[0]


def _in_target_frame(points: np.ndarray, pair) -> np.ndarray:
    """Shape points mapped like the target of a view-protocol pair: ``T((x - c) s)``."""
    scaled = (points - np.asarray(pair.meta["center"])) * pair.meta["scale"]
    transform = pair.gt_transform.astype(np.float64)
    return scaled @ transform[:3, :3].T + transform[:3, 3]


def test_modelnet_airplanes_airplane_protocol(shared_data):
    dataset = build_dataset(
        {
            "name": "modelnet40",
            "root": str(shared_data / "modelnet40_normal_resampled"),
            "categories": "airplane",
            "split": "train",
        }
    )
    assert len(dataset.shapes) == 60 and len(dataset) == 60 * 18
    pair = dataset[18 * 7 + 4]
    assert pair.meta["shape"] == "airplane_0008" and pair.meta["view"] == 4
    assert pair.src_xyz.shape == pair.tgt_xyz.shape == (1024, 3)
    # Both clouds are subsets of the shape's own points, mapped exactly like the target.
    shape = dataset.shapes.load(7)
    shape_points = cKDTree(_in_target_frame(shape.points, pair))
    assert shape_points.query(_source_moved(pair))[0].max() < 1e-4
    assert shape_points.query(pair.tgt_xyz)[0].max() < 1e-4
    visible = build_dataset(
        {
            "name": "modelnet40",
            "root": str(shared_data / "modelnet40_normal_resampled"),
            "categories": "airplane",
            "protocol": {"name": "airplane", "num_points": None},
        }
    )[18 * 7 + 4]
    assert len(visible.src_xyz) < 0.5 * len(shape.points), "the source should be a partial view"


def _source_moved(pair) -> np.ndarray:
    """The source moved by the GT transform."""
    transform = pair.gt_transform.astype(np.float64)
    return pair.src_xyz @ transform[:3, :3].T + transform[:3, 3]


def test_smpl_bodies_human_protocol(shared_data):
    root = shared_data / "meshes" / "odedstein" / "human"
    dataset = build_dataset({"name": "mesh_folder", "root": str(root), "protocol": "human"})
    assert len(dataset) == 3 * 50
    pair = dataset[50 + 13]
    assert pair.meta["shape"] == "human_neutral"
    mesh = read_mesh(root / "human_neutral.obj")
    surface, _ = trimesh.sample.sample_surface(mesh, 200_000, seed=0)
    surface_tree = cKDTree(_in_target_frame(surface, pair))
    assert np.median(surface_tree.query(_source_moved(pair))[0]) < 0.01
    covered = cKDTree(_source_moved(pair)).query(pair.tgt_xyz)[0]
    assert (covered < 0.03).mean() < 0.75, "the source should be a partial view of the body"


def test_threedmatch_pair_is_aligned_by_gt_log(shared_data):
    dataset = build_dataset(
        {
            "name": "threedmatch",
            "root": str(shared_data / "3dmatch" / "redkitchen_0_4"),
            "gt_log": str(shared_data / "3dmatch/geotransformer_demo/benchmarks/3DMatch/7-scenes-redkitchen/gt.log"),
            "skip_missing": True,
            **DENSE,
            "dense_points": 40000,
        }
    )
    assert len(dataset) == 1
    pair = dataset[0]
    assert (pair.meta["source"], pair.meta["target"]) == ("cloud_bin_4", "cloud_bin_0")
    assert pair.meta["overlap"] == pytest.approx(0.5422)
    aligned = (_distances(pair) < 0.0375).mean()
    assert aligned > 0.4
    assert (_distances(pair, np.eye(4)) < 0.0375).mean() < 0.5 * aligned


def test_seven_scenes_pairs_twenty_frames_apart(shared_data):
    dataset = build_dataset(
        {
            "name": "rgbd_sequence",
            "root": str(shared_data / "rgbd" / "7scenes_first_half" / "data"),
            "pixel_stride": 4,
            **DENSE,
        }
    )
    assert dataset.layout == "7scenes" and dataset.intrinsics.fx == 585
    for index in (0, 120):
        pair = dataset[index]
        assert pair.meta["target"] - pair.meta["source"] == 20
        distance = _distances(pair)
        assert (distance < 0.02).mean() > 0.7
        assert np.median(distance) < 0.6 * np.median(_distances(pair, np.eye(4)))
    paper = build_dataset({"name": "rgbd_sequence", "root": str(shared_data / "rgbd" / "7scenes_first_half" / "data")})[
        0
    ]
    assert pair.gt_transform is not None and paper.src_xyz.shape == (2048, 3)
    assert np.abs(np.concatenate([paper.src_xyz, paper.tgt_xyz])).max() == pytest.approx(5.0)


def test_redwood_style_sequence_with_camera_json(shared_data):
    folder = shared_data / "rgbd" / "open3d_synthetic"
    dataset = build_dataset(
        {
            "name": "rgbd_sequence",
            "root": str(folder / "RGBD"),
            "frame_gap": 4,
            "intrinsics": str(folder / "camera_primesense.json"),
            **DENSE,
        }
    )
    assert dataset.layout == "folder" and len(dataset) == 1
    assert (_distances(dataset[0]) < 0.01).mean() > 0.7


def test_tum_depth_frame_scale(shared_data):
    folder = shared_data / "rgbd" / "open3d_synthetic"
    depth = read_depth_image(folder / "RGBD" / "other_formats" / "TUM_depth.png")
    intrinsics = read_intrinsics(folder / "camera_primesense.json")
    points = depth_to_points(depth, intrinsics, depth_scale=5000.0)
    assert len(points) > 0.5 * depth.size
    assert 0.5 < np.median(points[:, 2]) < 5.0, "TUM depth is 5000 units per metre"
    with pytest.raises(ValueError, match="single-channel 16-bit"):
        read_depth_image(folder / "RGBD" / "other_formats" / "TUM_color.png")
