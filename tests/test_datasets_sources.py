"""Every dataset source on small generated files, and clear errors for bad input."""

from __future__ import annotations

import json

import h5py
import numpy as np
import open3d as o3d
import pytest
import trimesh
from PIL import Image
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from linereg.datasets import build_dataset
from linereg.datasets.formats import read_depth_image, read_log, read_overlap_log
from linereg.datasets.procedural import procedural_shape
from linereg.datasets.rgbd import depth_to_points
from linereg.io import write_point_cloud, write_transform


def _aligned_fraction(pair, tolerance: float) -> float:
    """Fraction of source points within ``tolerance`` of the target after the GT transform."""
    transform = pair.gt_transform.astype(np.float64)
    moved = pair.src_xyz @ transform[:3, :3].T + transform[:3, 3]
    distance, _ = cKDTree(pair.tgt_xyz).query(moved)
    return float((distance < tolerance).mean())


def _rigid(rng: np.random.Generator, angle_deg: float, translation: float) -> np.ndarray:
    """A random rigid transform with the given rotation angle and translation norm."""
    transform = np.eye(4)
    axis = rng.normal(size=3)
    transform[:3, :3] = Rotation.from_rotvec(np.radians(angle_deg) * axis / np.linalg.norm(axis)).as_matrix()
    direction = rng.normal(size=3)
    transform[:3, 3] = translation * direction / np.linalg.norm(direction)
    return transform


def _log_block(i: int, j: int, n: int, transform: np.ndarray) -> str:
    rows = "\n".join(" ".join(f"{v:.10f}" for v in row) for row in transform)
    return f"{i}\t{j}\t{n}\n{rows}\n"


# ----------------------------------------------------------------------------- mesh_folder


@pytest.fixture(scope="module")
def mesh_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("meshes")
    rng = np.random.default_rng(0)
    for category, split, name, suffix in [
        ("chair", "train", "chair_0001", ".off"),
        ("chair", "test", "chair_0002", ".obj"),
        ("lamp", "train", "lamp_0001", ".ply"),
        ("lamp", "test", "lamp_0002", ".stl"),
    ]:
        (root / category / split).mkdir(parents=True, exist_ok=True)
        mesh = procedural_shape(rng, min_parts=2, max_parts=3)
        mesh.apply_scale(40.0)
        mesh.export(root / category / split / f"{name}{suffix}")
    return root


def test_mesh_folder_reads_every_format_with_filters(mesh_root):
    everything = build_dataset(
        {"name": "mesh_folder", "root": str(mesh_root), "protocol": {"name": "airplane", "num_views": 2}}
    )
    assert len(everything) == 8
    assert {everything.shapes.load(i).meta["category"] for i in range(4)} == {"chair", "lamp"}
    lamps = build_dataset(
        {
            "name": "mesh_folder",
            "root": str(mesh_root),
            "categories": ["lamp"],
            "split": "test",
            "protocol": {"name": "human", "num_views": 3},
        }
    )
    assert len(lamps) == 3
    pair = lamps[1]
    assert pair.meta["shape"] == "lamp_0002" and pair.meta["file"].endswith(".stl")
    assert pair.src_xyz.shape == (1024, 3) and np.abs(pair.src_xyz).max() <= 1 + 1e-5
    assert _aligned_fraction(pair, 0.06) > 0.8


def test_mesh_folder_random_split_partitions_the_shapes(mesh_root):
    config = {"name": "mesh_folder", "root": str(mesh_root), "split_rule": "random", "train_fraction": 0.5}
    train = build_dataset({**config, "split": "train"}).shapes
    test = build_dataset({**config, "split": "test"}).shapes
    names = [train.load(i).name for i in range(len(train))] + [test.load(i).name for i in range(len(test))]
    assert len(train) == len(test) == 2 and len(set(names)) == 4


def test_mesh_folder_views_split_holds_out_camera_stops(mesh_root):
    config = {
        "name": "mesh_folder",
        "root": str(mesh_root),
        "split_rule": "views",
        "train_fraction": 0.75,
        "protocol": {"name": "human", "num_views": 4},
    }
    train = build_dataset({**config, "split": "train"})
    test = build_dataset({**config, "split": "test"})
    assert len(train.shapes) == len(test.shapes) == 4
    assert len(train.views) == 3 and len(test.views) == 1 and not set(train.views) & set(test.views)
    assert len(train) == 12 and len(test) == 4
    assert test[1].meta["shape"] == test.shapes.load(1).name
    assert not np.allclose(train[0].gt_transform, test[0].gt_transform)
    with pytest.raises(ValueError, match="split must be one of"):
        build_dataset({**config, "split": "val"})


def test_mesh_folder_held_out_split_tests_on_the_named_shapes_only(mesh_root):
    config = {
        "name": "mesh_folder",
        "root": str(mesh_root),
        "split_rule": "held_out",
        "held_out": ["lamp_0002"],
        "protocol": {"name": "human", "num_views": 2},
    }
    train, test = (build_dataset({**config, "split": split}) for split in ("train", "test"))
    train_names = {train.shapes.load(i).name for i in range(len(train.shapes))}
    assert train_names == {"chair_0001", "chair_0002", "lamp_0001"}
    assert [test.shapes.load(i).name for i in range(len(test.shapes))] == ["lamp_0002"]
    assert len(train) == 6 and len(test) == 2 and list(test.views) == [0, 1]  # every view of each shape
    assert train.shapes.describe() != test.shapes.describe()  # distinct cache keys
    with pytest.raises(ValueError, match=r"held_out names \['sofa_0001'\] are no mesh .*'chair_0001'"):
        build_dataset({**config, "held_out": ["sofa_0001"], "split": "test"})
    with pytest.raises(ValueError, match="split_rule='held_out' needs held_out"):
        build_dataset({**config, "held_out": None, "split": "test"})
    with pytest.raises(ValueError, match=r"held_out=.*needs split_rule='held_out', got 'views'"):
        build_dataset({**config, "split_rule": "views", "split": "test"})


def test_mixed_target_alternates_view_and_whole_pairs_of_the_same_views(mesh_root):
    def pairs(target: str):
        protocol = {"name": "airplane", "num_views": 2, "num_points": 64, "target": target}
        return build_dataset(
            {"name": "mesh_folder", "root": str(mesh_root), "categories": "lamp", "protocol": protocol}
        )

    mixed, view, whole = pairs("mixed"), pairs("view"), pairs("whole")
    assert [mixed.protocol.target_of(i) for i in range(4)] == ["view", "whole", "view", "whole"]
    for index, same in ((0, view), (1, whole), (2, view), (3, whole)):  # pair i of a shape is view i % 2
        np.testing.assert_array_equal(mixed[index].tgt_xyz, same[index].tgt_xyz)
        np.testing.assert_array_equal(mixed[index].src_xyz, same[index].src_xyz)
    with pytest.raises(ValueError, match="target must be one of"):
        pairs("both")


def test_anisotropic_scale_stretches_both_clouds_alike(mesh_root):
    def pair(anisotropic_scale: float):
        protocol = {"name": "human", "num_views": 2, "anisotropic_scale": anisotropic_scale}
        config = {"name": "mesh_folder", "root": str(mesh_root), "categories": "lamp", "protocol": protocol}
        return build_dataset(config)[1]

    plain, stretched = pair(0.0), pair(0.3)
    assert _aligned_fraction(stretched, 0.06) > 0.8  # the label still aligns the stretched pair
    extents = [np.ptp(p.tgt_xyz @ p.gt_transform[:3, :3], axis=0) for p in (plain, stretched)]
    assert not np.allclose(extents[0] / extents[0].max(), extents[1] / extents[1].max(), atol=0.02)
    np.testing.assert_allclose(np.linalg.norm(stretched.src_normals, axis=1), 1, atol=1e-5)
    with pytest.raises(ValueError, match=r"anisotropic_scale must be in \[0, 1\)"):
        pair(1.0)


def test_mesh_folder_errors(tmp_path, mesh_root):
    with pytest.raises(FileNotFoundError, match="mesh folder not found"):
        build_dataset({"name": "mesh_folder", "root": str(tmp_path / "nowhere")})
    with pytest.raises(FileNotFoundError, match="no mesh files"):
        build_dataset({"name": "mesh_folder", "root": str(tmp_path)})
    with pytest.raises(ValueError, match=r"unknown categor\(ies\) \['sofa'\].*'chair', 'lamp'"):
        build_dataset({"name": "mesh_folder", "root": str(mesh_root), "categories": "sofa"})
    (tmp_path / "empty.off").write_text("OFF\n0 0 0\n")
    dataset = build_dataset({"name": "mesh_folder", "root": str(tmp_path)})
    with pytest.raises(ValueError, match=r"empty\.off"):
        dataset[0]


# ----------------------------------------------------------------------------- modelnet40


def _surface_cloud(seed: int, count: int) -> tuple[np.ndarray, np.ndarray]:
    mesh = procedural_shape(np.random.default_rng(seed))
    points, faces = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return points.astype(np.float32), mesh.face_normals[faces].astype(np.float32)


@pytest.fixture(scope="module")
def modelnet_text_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("modelnet40_normal_resampled")
    for name in ("airplane_0001", "airplane_0626", "airplane_0627", "person_0089"):
        category = name.rsplit("_", 1)[0]
        (root / category).mkdir(exist_ok=True)
        points, normals = _surface_cloud(int(name[-4:]), 3000)
        np.savetxt(root / category / f"{name}.txt", np.hstack([points, normals]), fmt="%.6f", delimiter=",")
    return root


def test_modelnet40_text_official_split_and_categories(modelnet_text_root):
    config = {"name": "modelnet40", "root": str(modelnet_text_root), "categories": "airplane"}
    train = build_dataset({**config, "split": "train"})
    test = build_dataset({**config, "split": "test"})
    assert [train.shapes.load(i).name for i in range(len(train.shapes))] == ["airplane_0001", "airplane_0626"]
    assert [test.shapes.load(i).name for i in range(len(test.shapes))] == ["airplane_0627"]
    assert len(train) == 2 * 18
    pair = test[5]
    assert pair.meta["category"] == "airplane" and pair.src_xyz.shape == (1024, 3)
    assert _aligned_fraction(pair, 0.08) > 0.3
    person = build_dataset(
        {"name": "modelnet40", "root": str(modelnet_text_root), "categories": ["person"], "split": "test"}
    )
    assert person.shapes.load(0).name == "person_0089"


def test_modelnet40_split_files_win_over_numbering(modelnet_text_root, tmp_path):
    for path in modelnet_text_root.rglob("*.txt"):
        target = tmp_path / path.relative_to(modelnet_text_root)
        target.parent.mkdir(exist_ok=True)
        target.symlink_to(path)
    (tmp_path / "modelnet40_test.txt").write_text("airplane_0001\n")
    test = build_dataset({"name": "modelnet40", "root": str(tmp_path), "split": "test"})
    assert len(test.shapes) == 1 and test.shapes.load(0).name == "airplane_0001"


def test_modelnet40_paper_random_split(modelnet_text_root):
    config = {
        "name": "modelnet40",
        "root": str(modelnet_text_root),
        "categories": "airplane",
        "split_rule": "random",
        "train_fraction": 2 / 3,
    }
    train, test = (build_dataset({**config, "split": s}).shapes for s in ("train", "test"))
    assert len(train) == 2 and len(test) == 1
    assert test.load(0).name not in {train.load(0).name, train.load(1).name}


def test_modelnet40_hdf5_with_crop_protocol(tmp_path):
    clouds = [_surface_cloud(seed, 2048) for seed in range(3)]
    for split, rows, labels in (("train", [0, 1], [0, 1]), ("test", [2], [0])):
        with h5py.File(tmp_path / f"ply_data_{split}0.h5", "w") as archive:
            archive["data"] = np.stack([clouds[r][0] for r in rows])
            archive["normal"] = np.stack([clouds[r][1] for r in rows])
            archive["label"] = np.array(labels, dtype=np.uint8)[:, None]
    (tmp_path / "shape_names.txt").write_text("airplane\nbathtub\n")
    dataset = build_dataset(
        {"name": "modelnet40", "root": str(tmp_path), "categories": "airplane", "protocol": "rpmnet_crop"}
    )
    assert len(dataset) == 1
    pair = dataset[0]
    assert pair.meta["row"] == 0 and pair.meta["category"] == "airplane"
    assert pair.src_xyz.shape == (717, 3) and pair.src_normals.shape == (717, 3)
    everything = build_dataset({"name": "modelnet40", "root": str(tmp_path), "split": "all"})
    assert len(everything) == 3 * 18


def test_modelnet40_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="ModelNet40 folder not found"):
        build_dataset({"name": "modelnet40", "root": str(tmp_path / "missing")})
    with pytest.raises(FileNotFoundError, match="no ModelNet40 text files"):
        build_dataset({"name": "modelnet40", "root": str(tmp_path)})
    (tmp_path / "ply_data_train0.h5").touch()
    with pytest.raises(FileNotFoundError, match=r"shape_names\.txt"):
        build_dataset({"name": "modelnet40", "root": str(tmp_path)})
    with pytest.raises(ValueError, match="'held_out' is a mesh folder's rule"):
        build_dataset({"name": "modelnet40", "root": str(tmp_path), "split_rule": "held_out"})


# ----------------------------------------------------------------------------- pairs_folder


def test_pairs_folder_labelled_and_unlabelled(tmp_path):
    rng = np.random.default_rng(1)
    points, normals = _surface_cloud(4, 3000)
    transform = _rigid(rng, 20, 0.3)
    labelled, unlabelled = tmp_path / "labelled", tmp_path / "unlabelled"
    write_point_cloud(labelled / "scan_src.ply", points, normals)
    write_point_cloud(labelled / "scan_tgt.ply", (points @ transform[:3, :3].T + transform[:3, 3]).astype(np.float32))
    write_transform(labelled / "scan_gt.txt", transform)
    write_point_cloud(unlabelled / "a_src.xyz", points)
    write_point_cloud(unlabelled / "a_tgt.npy", points[::2])

    pair = build_dataset({"name": "pairs_folder", "root": str(labelled)})[0]
    assert pair.src_xyz.shape == (3000, 3) and pair.meta["name"] == "scan"
    np.testing.assert_allclose(pair.gt_transform, transform, atol=1e-6)
    assert _aligned_fraction(pair, 1e-4) == 1.0
    np.testing.assert_allclose(pair.src_normals, normals, atol=1e-6)
    assert pair.tgt_normals.shape == (3000, 3)

    scaled = build_dataset({"name": "pairs_folder", "root": str(labelled), "num_points": 512, "half_extent": 1.0})[0]
    assert scaled.src_xyz.shape == (512, 3) and np.abs(scaled.src_xyz).max() <= 1 + 1e-5
    assert _aligned_fraction(scaled, 0.15) > 0.9

    unlabeled = build_dataset({"name": "pairs_folder", "root": str(unlabelled)})[0]
    assert unlabeled.gt_transform is None and unlabeled.tgt_xyz.shape == (1500, 3)
    assert unlabeled.src_normals is not None


def test_pairs_folder_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="pairs folder not found"):
        build_dataset({"name": "pairs_folder", "root": str(tmp_path / "missing")})
    with pytest.raises(FileNotFoundError, match="_src"):
        build_dataset({"name": "pairs_folder", "root": str(tmp_path)})
    points, _ = _surface_cloud(1, 100)
    write_point_cloud(tmp_path / "a_src.ply", points)
    with pytest.raises(ValueError, match=r"without both _src and _tgt files: \['a'\]"):
        build_dataset({"name": "pairs_folder", "root": str(tmp_path)})
    for name in ("a", "b"):
        write_point_cloud(tmp_path / f"{name}_src.ply", points)
        write_point_cloud(tmp_path / f"{name}_tgt.ply", points)
    write_transform(tmp_path / "a_gt.txt", np.eye(4))
    with pytest.raises(ValueError, match=r"for every pair or for none; missing for \['b'\]"):
        build_dataset({"name": "pairs_folder", "root": str(tmp_path)})


# ----------------------------------------------------------------------------- threedmatch


@pytest.fixture(scope="module")
def threedmatch_scene(tmp_path_factory):
    """Three fragments of one synthetic scene and the gt.log / gt_overlap.log relating them.

    Fragment k holds the scene points with x below a threshold (overlapping slabs), in its own
    frame; gt_overlap.log records the true share of fragment j lying inside fragment i.
    """
    root = tmp_path_factory.mktemp("threedmatch")
    scene = root / "7-scenes-synthetic"
    evaluation = root / "7-scenes-synthetic-evaluation"
    evaluation.mkdir()
    rng = np.random.default_rng(2)
    world, _ = _surface_cloud(7, 30000)
    world *= 2.0
    poses = [np.eye(4)] + [_rigid(rng, 15, 0.4) for _ in range(2)]  # fragment -> world
    limits = [-0.1, 0.5, 1.1]
    for k, pose in enumerate(poses):
        local = (world[world[:, 0] < limits[k]] - pose[:3, 3]) @ pose[:3, :3]
        write_point_cloud(scene / f"cloud_bin_{k}.ply", local.astype(np.float32))
    pairs = ((0, 1), (0, 2), (1, 2))
    blocks = [_log_block(i, j, 3, np.linalg.inv(poses[i]) @ poses[j]) for i, j in pairs]
    (evaluation / "gt.log").write_text("".join(blocks))
    overlaps = [float(np.mean(world[world[:, 0] < limits[j], 0] < limits[i])) for i, j in pairs]
    (evaluation / "gt_overlap.log").write_text(
        "".join(f"{i},{j},{o:.4f}\n" for (i, j), o in zip(pairs, overlaps, strict=True))
    )
    return scene


def test_threedmatch_pairs_follow_the_gt_log_convention(threedmatch_scene):
    dataset = build_dataset({"name": "threedmatch", "root": str(threedmatch_scene), "num_points": 1024})
    assert len(dataset) == 3
    pair = dataset[0]
    assert (pair.meta["source"], pair.meta["target"]) == ("cloud_bin_1", "cloud_bin_0")
    assert pair.src_xyz.shape == (1024, 3)
    assert np.abs(np.concatenate([pair.src_xyz, pair.tgt_xyz])).max() == pytest.approx(5.0)
    dense = {"num_points": None, "dense_points": None, "half_extent": None}
    metric = build_dataset({"name": "threedmatch", "root": str(threedmatch_scene), **dense})
    for index in range(3):
        overlap = metric[index].meta["overlap"]
        assert 0.2 < overlap < 1
        assert _aligned_fraction(metric[index], 1e-4) == pytest.approx(overlap, abs=1e-3)


def test_threedmatch_overlap_filter(threedmatch_scene):
    config = {"name": "threedmatch", "root": str(threedmatch_scene)}
    overlaps = build_dataset(config).overlaps
    middle = sorted(overlaps.values())[1]
    kept = build_dataset({**config, "min_overlap": middle})
    assert len(kept) == 2 and all(overlaps[(e.i, e.j)] >= middle for e in kept.entries)
    low = build_dataset({**config, "max_overlap": middle - 1e-3})
    assert len(low) == 1 and overlaps[(low.entries[0].i, low.entries[0].j)] < middle


def test_read_log_returns_exactly_rigid_poses_of_a_published_precision(tmp_path):
    """Published logs print 9 digits of a rotation rigid to about 1e-4; read_log repairs that much."""
    rotation = Rotation.from_euler("xyz", [10.0, -20.0, 30.0], degrees=True).as_matrix()
    logged = np.eye(4)
    logged[:3, :3] = rotation * (1.0 + 5e-5)
    logged[:3, 3] = [0.1, -0.2, 0.3]
    (tmp_path / "gt.log").write_text(_log_block(0, 1, 2, logged))

    (entry,) = read_log(tmp_path / "gt.log")

    assert np.allclose(entry.transform[:3, :3].T @ entry.transform[:3, :3], np.eye(3), atol=1e-12)
    assert np.allclose(entry.transform[:3, :3], rotation, atol=1e-9)
    assert np.array_equal(entry.transform[:3, 3], logged[:3, 3]) and np.array_equal(entry.transform[3], [0, 0, 0, 1])


def test_threedmatch_errors(threedmatch_scene, tmp_path):
    with pytest.raises(FileNotFoundError, match=r"no gt\.log"):
        build_dataset({"name": "threedmatch", "root": str(tmp_path)})
    bad_log = tmp_path / "gt.log"
    bad_log.write_text("0 1\n" + "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(ValueError, match=r"gt.log: line 1: expected a block header of 3 integers"):
        build_dataset({"name": "threedmatch", "root": str(threedmatch_scene), "gt_log": str(bad_log)})
    bad_log.write_text("0 1 3\n1 0 0 0\n0 1 0 0\n")
    with pytest.raises(ValueError, match="not a multiple of 5"):
        read_log(bad_log)
    bad_log.write_text("0 1 3\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 x\n")
    with pytest.raises(ValueError, match="line 5: expected 4 numbers"):
        read_log(bad_log)
    bad_log.write_text("0 1 3\n2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(ValueError, match="not a rigid transform"):
        read_log(bad_log)
    bad_log.write_text(_log_block(0, 5, 6, np.eye(4)))
    with pytest.raises(FileNotFoundError, match=r"cloud_bin_5.ply.*skip_missing=True"):
        build_dataset({"name": "threedmatch", "root": str(threedmatch_scene), "gt_log": str(bad_log)})
    with pytest.raises(ValueError, match="no 3DMatch pairs left"):
        build_dataset(
            {"name": "threedmatch", "root": str(threedmatch_scene), "gt_log": str(bad_log), "skip_missing": True}
        )
    with pytest.raises(ValueError, match="need overlap ratios"):
        build_dataset(
            {"name": "threedmatch", "root": str(threedmatch_scene), "gt_log": str(bad_log), "min_overlap": 0.3}
        )
    (tmp_path / "overlap.log").write_text("0,1\n")
    with pytest.raises(ValueError, match="line 1: expected 3 numbers"):
        read_overlap_log(tmp_path / "overlap.log")


# ----------------------------------------------------------------------------- rgbd_sequence

WIDTH, HEIGHT = 160, 120
FX = FY = 140.0
CX, CY = 79.5, 59.5
DENSE = {"num_points": None, "dense_points": None, "half_extent": None, "pixel_stride": 1}


def _assert_frames_aligned(pair) -> None:
    """The GT puts most source pixels within a pixel footprint (~1.5 cm) of the target."""
    transform = pair.gt_transform.astype(np.float64)
    moved = pair.src_xyz @ transform[:3, :3].T + transform[:3, 3]
    distance, _ = cKDTree(pair.tgt_xyz).query(moved)
    assert np.median(distance) < 0.015
    assert np.mean(distance < 0.03) > 0.75


def _room() -> o3d.t.geometry.RaycastingScene:
    """A 4 m room with a few boxes, as a ray-casting scene."""
    parts = [trimesh.creation.box(extents=[4.0, 3.0, 5.0])]
    for extents, position in (([0.6, 1.0, 0.5], [-0.8, 0.4, 1.6]), ([0.4, 0.4, 0.9], [0.9, -0.6, 1.2])):
        box = trimesh.creation.box(extents=extents)
        box.apply_translation(position)
        parts.append(box)
    mesh = trimesh.util.concatenate(parts)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32))
    )
    return scene


def _render_depth(scene, pose: np.ndarray, scale: float) -> np.ndarray:
    """16-bit depth image (raw units ``scale`` per metre) seen by a camera-to-world ``pose``."""
    intrinsic = o3d.core.Tensor([[FX, 0, CX], [0, FY, CY], [0, 0, 1]], dtype=o3d.core.float64)
    extrinsic = o3d.core.Tensor(np.linalg.inv(pose), dtype=o3d.core.float64)
    rays = scene.create_rays_pinhole(intrinsic, extrinsic, WIDTH, HEIGHT)
    t_hit = scene.cast_rays(rays)["t_hit"].numpy()
    rays = rays.numpy()
    world = rays[..., :3] + t_hit[..., None] * rays[..., 3:]
    camera = (world - pose[:3, 3]) @ pose[:3, :3]
    depth = np.where(np.isfinite(t_hit), camera[..., 2] * scale, 0)
    return np.round(depth).astype(np.uint16)


@pytest.fixture(scope="module")
def camera_poses():
    rng = np.random.default_rng(3)
    poses = [np.eye(4)]
    for _ in range(2):
        poses.append(poses[-1] @ _rigid(rng, 6, 0.1))
    return poses


def test_seven_scenes_layout(tmp_path, camera_poses):
    scene = _room()
    for k, pose in enumerate(camera_poses):
        Image.fromarray(_render_depth(scene, pose, 1000.0)).save(tmp_path / f"frame-{2 * k:06d}.depth.png")
        np.savetxt(tmp_path / f"frame-{2 * k:06d}.pose.txt", pose)
    np.savetxt(tmp_path / "camera-intrinsics.txt", [[FX, 0, CX], [0, FY, CY], [0, 0, 1]])
    dataset = build_dataset({"name": "rgbd_sequence", "root": str(tmp_path), "frame_gap": 2})
    assert dataset.layout == "7scenes" and len(dataset) == 2
    pair = dataset[1]
    assert (pair.meta["source"], pair.meta["target"]) == (2, 4)
    assert pair.src_xyz.shape == (2048, 3)
    assert np.abs(np.concatenate([pair.src_xyz, pair.tgt_xyz])).max() == pytest.approx(5.0)
    dense = build_dataset({"name": "rgbd_sequence", "root": str(tmp_path), "frame_gap": 2, **DENSE})
    _assert_frames_aligned(dense[1])
    unlabeled = build_dataset({"name": "rgbd_sequence", "root": str(tmp_path), "frame_gap": 4, "use_poses": False})
    assert len(unlabeled) == 1 and unlabeled[0].gt_transform is None
    late = build_dataset({"name": "rgbd_sequence", "root": str(tmp_path), "frame_gap": 2, "frame_range": [2, 100]})
    assert [(s.number, t.number) for s, t in late.pairs] == [(2, 4)]
    with pytest.raises(ValueError, match="frame_range must be"):
        build_dataset({"name": "rgbd_sequence", "root": str(tmp_path), "frame_range": [4, 2]})


def test_exported_frames_are_a_scan_folder_labelled_by_their_camera_poses(tmp_path, camera_poses):
    """``scripts/export_rgbd_scans.py``: every STEP-th frame as a PLY and the camera poses as a
    ``.conf`` that ``scan_folder`` reads back exactly (``write_conf`` inverts ``read_conf``)."""
    from linereg.datasets.formats import read_conf
    from scripts.export_rgbd_scans import export_frames, main

    scene, sequence = _room(), tmp_path / "sequence"
    sequence.mkdir()
    for k, pose in enumerate(camera_poses):
        Image.fromarray(_render_depth(scene, pose, 1000.0)).save(sequence / f"frame-{2 * k:06d}.depth.png")
        np.savetxt(sequence / f"frame-{2 * k:06d}.pose.txt", pose)
    np.savetxt(sequence / "camera-intrinsics.txt", [[FX, 0, CX], [0, FY, CY], [0, 0, 1]])
    files = export_frames(sequence, tmp_path / "scans", (0, 5, 2), pixel_stride=1)
    assert [file.name for file in files] == ["scan_0.ply", "scan_2.ply", "scan_4.ply"]
    written = read_conf(tmp_path / "scans" / "poses.conf")
    assert all(np.allclose(written[f"scan_{2 * k}.ply"], pose, atol=1e-7) for k, pose in enumerate(camera_poses))
    folder = {"name": "scan_folder", "root": str(tmp_path / "scans"), "poses": "poses.conf"}
    pair = build_dataset({**folder, "num_points": None, "dense_points": None, "half_extent": None})[1]
    _assert_frames_aligned(pair)
    assert main([str(sequence), str(tmp_path / "one"), "--frames", "0", "2", "2"]) == 2  # one frame only
    assert main([str(tmp_path / "missing"), str(tmp_path / "out")]) == 2


def test_tum_layout(tmp_path, camera_poses):
    scene = _room()
    (tmp_path / "depth").mkdir()
    depth_lines, pose_lines = ["# depth maps"], ["# timestamp tx ty tz qx qy qz qw"]
    for k, pose in enumerate(camera_poses):
        stamp = 100.0 + 0.5 * k
        Image.fromarray(_render_depth(scene, pose, 5000.0)).save(tmp_path / "depth" / f"{stamp:.6f}.png")
        depth_lines.append(f"{stamp:.6f} depth/{stamp:.6f}.png")
        quaternion = Rotation.from_matrix(pose[:3, :3]).as_quat()  # x y z w
        values = [*pose[:3, 3], *quaternion]
        pose_lines.append(f"{stamp + 0.004:.6f} " + " ".join(f"{v:.9f}" for v in values))
    (tmp_path / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (tmp_path / "groundtruth.txt").write_text("\n".join(pose_lines) + "\n")
    dataset = build_dataset(
        {"name": "rgbd_sequence", "root": str(tmp_path), "frame_gap": 1, "intrinsics": [FX, FY, CX, CY], **DENSE}
    )
    assert dataset.layout == "tum" and dataset.depth_scale == 5000.0 and len(dataset) == 2
    _assert_frames_aligned(dataset[0])


def test_folder_layout_with_redwood_log_and_json_intrinsics(tmp_path, camera_poses):
    scene = _room()
    (tmp_path / "depth").mkdir()
    for k, pose in enumerate(camera_poses):
        Image.fromarray(_render_depth(scene, pose, 1000.0)).save(tmp_path / "depth" / f"{k:05d}.png")
    (tmp_path / "trajectory.log").write_text("".join(_log_block(k, k, k + 1, p) for k, p in enumerate(camera_poses)))
    (tmp_path / "camera_intrinsics.json").write_text(
        json.dumps({"width": WIDTH, "height": HEIGHT, "intrinsic_matrix": [FX, 0, 0, 0, FY, 0, CX, CY, 1]})
    )
    dataset = build_dataset({"name": "rgbd_sequence", "root": str(tmp_path), "frame_gap": 2, **DENSE})
    assert dataset.layout == "folder" and dataset.intrinsics.cx == CX
    _assert_frames_aligned(dataset[0])


def test_depth_to_points_geometry():
    depth = np.zeros((4, 6), dtype=np.uint16)
    depth[2, 5] = 2000
    depth[0, 0] = 65535
    from linereg.datasets.formats import Intrinsics

    points = depth_to_points(depth, Intrinsics(100.0, 50.0, 3.0, 1.0), depth_scale=1000.0)
    np.testing.assert_allclose(points, [[(5 - 3) * 2 / 100, (2 - 1) * 2 / 50, 2.0]])


def test_rgbd_errors(tmp_path, camera_poses):
    with pytest.raises(FileNotFoundError, match="RGB-D sequence folder not found"):
        build_dataset({"name": "rgbd_sequence", "root": str(tmp_path / "missing")})
    with pytest.raises(FileNotFoundError, match="not a recognised RGB-D sequence"):
        build_dataset({"name": "rgbd_sequence", "root": str(tmp_path)})
    (tmp_path / "depth").mkdir()
    colour = np.zeros((HEIGHT, WIDTH, 3), dtype=np.uint8)
    for k in range(2):
        Image.fromarray(colour).save(tmp_path / "depth" / f"{k}.png")
    dataset = build_dataset({"name": "rgbd_sequence", "root": str(tmp_path), "frame_gap": 1})
    with pytest.raises(ValueError, match=r"0\.png: depth image must be single-channel 16-bit.*'RGB'"):
        dataset[0]
    with pytest.raises(ValueError, match="no frame pairs 5 frames apart"):
        build_dataset({"name": "rgbd_sequence", "root": str(tmp_path), "frame_gap": 5})
    Image.fromarray(np.zeros((4, 4), dtype=np.uint8)).save(tmp_path / "gray.png")
    with pytest.raises(ValueError, match="got Pillow mode 'L'"):
        read_depth_image(tmp_path / "gray.png")
    (tmp_path / "pose.txt").write_text("0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match="1 poses for 2 depth images"):
        build_dataset({"name": "rgbd_sequence", "root": str(tmp_path), "frame_gap": 1})
