"""Download ModelNet40 for the Airplane experiment (and RPM-Net's crop protocol).

Usage::

    python scripts/download_modelnet40.py --root data/modelnet40 [--format hdf5|resampled|off]
    python scripts/download_modelnet40.py --list        # mirrors and checksums, no download

Formats (the ``modelnet40`` dataset reads the first two; ``mesh_folder`` reads the third):

* ``hdf5``: ``modelnet40_ply_hdf5_2048`` (416 MB; 2048 points + normals per shape; RPM-Net's
  data). The original Stanford link is often down; Hugging Face and GitHub mirrors are tried.
  The extracted ``ply_data_*.h5`` files are checked against their published MD5 sums.
* ``resampled``: ``modelnet40_normal_resampled`` (1.6 GB; 10 000 points + normals per shape;
  the paper's Airplane experiment). No checksum is published for it.
* ``off``: Princeton's ``ModelNet40.zip`` meshes (2 GB, ``<class>/{train,test}/*.off``),
  for the mesh ray-casting path. No checksum is published.

When every mirror fails, the script prints which file to fetch by hand and where to put it;
rerunning it then verifies and extracts that file.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from scripts._download import DownloadError, IntegrityError, Resource, fetch_and_extract  # noqa: E402

# MD5 sums of the extracted HDF5 files, as published in torchvision-style ModelNet40 loaders.
HDF5_MEMBER_MD5 = {
    "modelnet40_ply_hdf5_2048/ply_data_train0.h5": "3176385ffc31a7b6b5af22191fd920d1",
    "modelnet40_ply_hdf5_2048/ply_data_train1.h5": "e3f613fb500559403b34925112754dc4",
    "modelnet40_ply_hdf5_2048/ply_data_train2.h5": "0c56e233a090ff87c3049d4ce08e7d8b",
    "modelnet40_ply_hdf5_2048/ply_data_train3.h5": "9d2af465adfa33a3285c369f3ca66c45",
    "modelnet40_ply_hdf5_2048/ply_data_train4.h5": "dff38de489b2c41bfaeded86c2208984",
    "modelnet40_ply_hdf5_2048/ply_data_test0.h5": "e9732e6d83b09e79e9a7617df058adee",
    "modelnet40_ply_hdf5_2048/ply_data_test1.h5": "aba4b12a67c34391cc3c015a6f08ed4b",
}

RESOURCES = {
    "hdf5": Resource(
        name="modelnet40_ply_hdf5_2048.zip",
        urls=(
            "https://huggingface.co/datasets/Msun/modelnet40/resolve/main/modelnet40_ply_hdf5_2048.zip",
            "https://github.com/ma-xu/pointMLP-pytorch/releases/download/Modenet40_dataset/modelnet40_ply_hdf5_2048.zip",
            "https://shapenet.cs.stanford.edu/media/modelnet40_ply_hdf5_2048.zip",
        ),
        member_md5=HDF5_MEMBER_MD5,
        note="no archive checksum is published; the seven .h5 files are checked after extraction",
    ),
    "resampled": Resource(
        name="modelnet40_normal_resampled.zip",
        urls=("https://shapenet.cs.stanford.edu/media/modelnet40_normal_resampled.zip",),
        note=(
            "no checksum published; other copies circulate on Kaggle "
            "(datasets/chenxaoyu/modelnet-normal-resampled, login needed): put the zip in --root"
        ),
    ),
    "off": Resource(
        name="ModelNet40.zip",
        urls=(
            "https://modelnet.cs.princeton.edu/ModelNet40.zip",
            "http://modelnet.cs.princeton.edu/ModelNet40.zip",
        ),
        note="no checksum published",
    ),
}

DATASET_FOLDERS = {
    "hdf5": "modelnet40_ply_hdf5_2048",
    "resampled": "modelnet40_normal_resampled",
    "off": "ModelNet40",
}

USAGE = {
    "hdf5": "{{name: modelnet40, root: {folder}, categories: airplane, protocol: rpmnet_crop}}",
    "resampled": "{{name: modelnet40, root: {folder}, categories: airplane}}",
    "off": (
        "{{name: mesh_folder, root: {folder}, categories: airplane, split: train, "
        "protocol: {{name: airplane, view_axis: [0, 0, 1]}}}}"
    ),
}


def describe() -> str:
    """Mirrors and integrity checks of every format."""
    lines = []
    for key, resource in RESOURCES.items():
        lines.append(f"[{key}] {resource.name}  (verification: {resource.integrity()})")
        lines += [f"    {url}" for url in resource.urls]
        if resource.note:
            lines.append(f"    note: {resource.note}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=Path("data/modelnet40"), help="download folder")
    parser.add_argument("--format", choices=sorted(RESOURCES), default="resampled")
    parser.add_argument("--list", action="store_true", help="print mirrors and checksums only")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    if args.list:
        print(describe())
        return 0
    started = time.perf_counter()
    resource = RESOURCES[args.format]
    try:
        fetch_and_extract(resource, args.root, args.root, progress=not args.quiet)
    except (DownloadError, IntegrityError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    folder = args.root / DATASET_FOLDERS[args.format]
    print(f"ModelNet40 ({args.format}) ready in {folder} ({time.perf_counter() - started:.0f} s)")
    print(f"use it with: {USAGE[args.format].format(folder=folder)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
