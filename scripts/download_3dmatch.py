"""Download the 3DMatch geometric-registration benchmark (fragments + gt.log) and 3DLoMatch logs.

Usage::

    python scripts/download_3dmatch.py --root data/3dmatch [--scenes 7-scenes-redkitchen ...]
    python scripts/download_3dmatch.py --list        # mirrors, no download

Per test scene this writes (the layout the ``threedmatch`` dataset reads)::

    <root>/<scene>/cloud_bin_<i>.ply                 official fragments (metres)
    <root>/<scene>-evaluation/gt.log, gt.info        official ground truth (p_i = T p_j)
    <root>/<scene>-evaluation/gt_overlap.log         overlap ratios (GeoTransformer's metadata)
    <root>/3DLoMatch/<scene>/gt.log, gt_overlap.log  3DLoMatch pairs (10-30 % overlap)

Then ``{name: threedmatch, root: <root>/<scene>, min_overlap: 0.7}`` gives the paper's
high-overlap pairs, and ``gt_log: <root>/3DLoMatch/<scene>/gt.log`` the 3DLoMatch ones.
No checksums are published for the Princeton archives (only their readability is checked).
The paper's training pairs come from DGR's preprocessed 3DMatch (``threedmatch.tgz`` of
chrischoy/DeepGlobalRegistration), a different layout that this project does not read.
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
    fetch,
    fetch_and_extract,
)

SCENES = (
    "7-scenes-redkitchen",
    "sun3d-home_at-home_at_scan1_2013_jan_1",
    "sun3d-home_md-home_md_scan9_2012_sep_30",
    "sun3d-hotel_uc-scan3",
    "sun3d-hotel_umd-maryland_hotel1",
    "sun3d-hotel_umd-maryland_hotel3",
    "sun3d-mit_76_studyroom-76-1studyroom2",
    "sun3d-mit_lab_hj-lab_hj_tea_nov_2_2012_scan1_erika",
)
PRINCETON_MIRRORS = (
    "https://3dvision.princeton.edu/projects/2016/3DMatch/downloads/scene-fragments",
    "http://vision.princeton.edu/projects/2016/3DMatch/downloads/scene-fragments",
)
# GeoTransformer's benchmark metadata (MIT), pinned to the commit described in the shared data.
GEOTRANSFORMER_METADATA = (
    "https://raw.githubusercontent.com/qinzheng93/GeoTransformer/"
    "e7a135af4c318ff3b8d7f6c963df094d7e4ea540/data/3DMatch/metadata/benchmarks"
)


def scene_archives(scene: str) -> list[Resource]:
    """The official fragment and evaluation archives of one scene."""
    return [
        Resource(name=f"{name}.zip", urls=tuple(f"{base}/{name}.zip" for base in PRINCETON_MIRRORS))
        for name in (scene, f"{scene}-evaluation")
    ]


def metadata_files(benchmark: str, scene: str) -> list[Resource]:
    """GeoTransformer's log files of one scene of ``"3DMatch"`` or ``"3DLoMatch"``."""
    names = ("gt_overlap.log",) if benchmark == "3DMatch" else ("gt.log", "gt.info", "gt_overlap.log")
    return [Resource(name=name, urls=(f"{GEOTRANSFORMER_METADATA}/{benchmark}/{scene}/{name}",)) for name in names]


def describe(scenes: list[str]) -> str:
    """Every file the script would fetch, with its mirrors."""
    lines = []
    for scene in scenes:
        resources = scene_archives(scene) + metadata_files("3DMatch", scene)
        resources += metadata_files("3DLoMatch", scene)
        for resource in resources:
            lines.append(f"{scene}: {resource.name} (verification: {resource.integrity()})")
            lines += [f"    {url}" for url in resource.urls]
    return "\n".join(lines)


def download_scene(root: Path, scene: str, *, progress: bool) -> None:
    """Fetch and lay out one scene (see the module docstring)."""
    archives = root / "archives"
    for archive in scene_archives(scene):
        fetch_and_extract(archive, archives, root, progress=progress)
    for resource in metadata_files("3DMatch", scene):
        fetch(resource, root / f"{scene}-evaluation", progress=progress)
    for resource in metadata_files("3DLoMatch", scene):
        fetch(resource, root / "3DLoMatch" / scene, progress=progress)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=Path("data/3dmatch"), help="download folder")
    parser.add_argument("--scenes", nargs="+", choices=SCENES, default=list(SCENES), metavar="SCENE")
    parser.add_argument("--list", action="store_true", help="print the files and mirrors only")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    if args.list:
        print(describe(args.scenes))
        return 0
    started = time.perf_counter()
    for scene in args.scenes:
        try:
            download_scene(args.root, scene, progress=not args.quiet)
        except (DownloadError, IntegrityError) as error:
            print(f"error: {error}", file=sys.stderr)
            return 1
    print(f"3DMatch scenes {args.scenes} ready in {args.root} ({time.perf_counter() - started:.0f} s)")
    print(f"use them with: {{name: threedmatch, root: {args.root / args.scenes[0]}}}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
