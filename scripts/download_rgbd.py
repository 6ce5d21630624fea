"""Download RGB-D sequences for the paper's Real dataset: Microsoft 7-Scenes and TUM RGB-D.

Usage::

    python scripts/download_rgbd.py --root data/rgbd --dataset 7scenes --scenes chess heads
    python scripts/download_rgbd.py --root data/rgbd --dataset tum --scenes freiburg1_xyz
    python scripts/download_rgbd.py --list                 # mirrors and checksums only

Layouts produced (both read by the ``rgbd_sequence`` dataset, ``layout: auto``)::

    <root>/7scenes/<scene>/seq-XX/frame-XXXXXX.{depth.png,pose.txt}   (depth mm, 585/320/240)
    <root>/tum/rgbd_dataset_<sequence>/{depth.txt,depth/,groundtruth.txt}  (depth / 5000)

7-Scenes archives are checked by size and SHA-256 as recorded by a public third-party
download script (Microsoft publishes none); TUM publishes no checksums (only the archive's
readability is checked). 7-Scenes is for non-commercial research use; TUM RGB-D is CC BY 4.0.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from scripts._download import (  # noqa: E402
    DownloadError,
    IntegrityError,
    Resource,
    extract,
    fetch_and_extract,
)

SEVEN_SCENES_MIRRORS = (
    "https://download.microsoft.com/download/2/8/5/28564B23-0828-408F-8631-23B1EFF1DAC8",
    "http://download.microsoft.com/download/2/8/5/28564B23-0828-408F-8631-23B1EFF1DAC8",
)
# (size in bytes, sha256) of each scene archive, as recorded by a third-party script.
SEVEN_SCENES_ARCHIVES = {
    "chess": (3079608937, "d00b5b8f904123ec136768ee0ebd8f72aebb5473630fb5d8ec352e70ae4859d0"),
    "fire": (2301204154, "735d577f471a116b3f190f9bd79026b7fccfc6dee220473499bdb2b93efd1955"),
    "heads": (956332240, "402f8760ba150100bda5360241b605383dc5f949c055863301bde1b45f6a7a5d"),
    "office": (4707873861, "c2bd101aae86c926d43ed92e080140b2e32d54ce14a5ce289b9aeca3472e7744"),
    "pumpkin": (2890874911, "53fd1cb4c2f50378abc112f48e8897138e2135f2848c8c2e094e8028af07a65f"),
    "redkitchen": (6141181406, "55f6aeabfd8308fbe02a6f37d1dbdbc4c087c3c6c84cb5fae062a90c43ffcba6"),
    "stairs": (1496412431, "3521a1a26acb98321918ec352f8b189d301c2e3cce2de1bf2eac424d003b3929"),
}
TUM_MIRRORS = (
    "https://cvg.cit.tum.de/rgbd/dataset",
    "https://vision.in.tum.de/rgbd/dataset",
)
TUM_SEQUENCES = (
    "freiburg1_xyz",
    "freiburg1_desk",
    "freiburg1_desk2",
    "freiburg1_room",
    "freiburg2_xyz",
    "freiburg2_desk",
    "freiburg3_long_office_household",
)


def seven_scenes_resource(scene: str) -> Resource:
    """The archive of one 7-Scenes scene."""
    size, sha256 = SEVEN_SCENES_ARCHIVES[scene]
    return Resource(
        name=f"{scene}.zip",
        urls=tuple(f"{base}/{scene}.zip" for base in SEVEN_SCENES_MIRRORS),
        size=size,
        sha256=sha256,
        note="size/sha256 recorded by a third-party script, not published by Microsoft",
    )


def tum_resource(sequence: str) -> Resource:
    """The archive of one TUM RGB-D sequence (e.g. ``freiburg1_xyz``)."""
    group = sequence.split("_", 1)[0]
    name = f"rgbd_dataset_{sequence}.tgz"
    return Resource(name=name, urls=tuple(f"{base}/{group}/{name}" for base in TUM_MIRRORS))


def resources(dataset: str, scenes: list[str]) -> list[Resource]:
    """The archives of the chosen scenes / sequences."""
    if dataset == "7scenes":
        return [seven_scenes_resource(scene) for scene in scenes]
    return [tum_resource(sequence) for sequence in scenes]


def extract_sequences(scene_dir: Path) -> list[Path]:
    """Extract the per-sequence ``seq-XX.zip`` archives found inside a 7-Scenes scene folder."""
    extracted = []
    for inner in sorted(scene_dir.glob("seq-*.zip")):
        target = scene_dir / inner.stem
        if not target.is_dir():
            extract(inner, scene_dir)
        extracted.append(target)
    return extracted


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=Path("data/rgbd"), help="download folder")
    parser.add_argument("--dataset", choices=("7scenes", "tum"), default="7scenes")
    parser.add_argument(
        "--scenes",
        nargs="+",
        metavar="NAME",
        help=f"7-Scenes scenes {sorted(SEVEN_SCENES_ARCHIVES)} or TUM sequences {list(TUM_SEQUENCES)}",
    )
    parser.add_argument("--list", action="store_true", help="print mirrors and checksums only")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    known = sorted(SEVEN_SCENES_ARCHIVES) if args.dataset == "7scenes" else list(TUM_SEQUENCES)
    scenes = args.scenes or known
    unknown = sorted(set(scenes) - set(known))
    if unknown:
        parser.error(f"unknown {args.dataset} name(s) {unknown}; choose from {known}")
    chosen = resources(args.dataset, scenes)
    if args.list:
        for resource in chosen:
            print(f"{resource.name} (verification: {resource.integrity()})")
            print("\n".join(f"    {url}" for url in resource.urls))
        return 0
    started = time.perf_counter()
    target = args.root / ("7scenes" if args.dataset == "7scenes" else "tum")
    for resource, scene in zip(chosen, scenes, strict=True):
        try:
            fetch_and_extract(resource, args.root / "archives", target, progress=not args.quiet)
        except (DownloadError, IntegrityError) as error:
            print(f"error: {error}", file=sys.stderr)
            return 1
        if args.dataset == "7scenes":
            extract_sequences(target / scene)
    print(f"{args.dataset} {scenes} ready in {target} ({time.perf_counter() - started:.0f} s)")
    example = target / scenes[0] / "seq-01" if args.dataset == "7scenes" else target / f"rgbd_dataset_{scenes[0]}"
    print(f"use it with: {{name: rgbd_sequence, root: {example}, frame_gap: 20}}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
