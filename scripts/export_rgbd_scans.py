"""Write an RGB-D sequence's depth frames as a folder of scans for ``dataset=scan_folder``.

    python scripts/export_rgbd_scans.py <sequence folder> <out folder> [--frames 400 500 5]

One PLY per chosen frame, ``scan_<number>.ply``: the depth image back-projected as the
``rgbd_sequence`` dataset does (any layout it reads; every ``--pixel-stride``-th pixel, camera
coordinates in metres). Where the sequence has camera poses, ``poses.conf`` holds each frame's
camera-to-world pose (a Stanford alignment file): ``dataset.poses=poses.conf`` labels the test
split of a fine-tuning run with it, and nothing else reads it. ``--frames START STOP STEP`` takes
the frames numbered ``START, START + STEP, ...`` below ``STOP``; ``--intrinsics FX FY CX CY`` a
sequence's camera where it ships no intrinsics file.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from linereg.datasets import build_dataset
from linereg.datasets.formats import write_conf
from linereg.io import write_point_cloud


def export_frames(
    root: Path,
    out: Path,
    frames: tuple[int, int, int],
    pixel_stride: int = 2,
    max_depth: float | None = None,
    intrinsics: list[float] | None = None,
) -> list[Path]:
    """Write the chosen frames of the sequence ``root`` into ``out`` (see the module docstring);
    the scan files in frame order.

    Raises:
        ValueError, FileNotFoundError: a bad sequence folder or a choice with fewer than 2 frames.
    """
    start, stop, step = frames
    if step < 1 or stop - start <= step:
        raise ValueError(f"--frames {start} {stop} {step}: at least 2 frames are needed (STEP >= 1)")
    settings = {"frame_gap": step, "frame_range": [start, stop], "pixel_stride": pixel_stride, "max_depth": max_depth}
    settings["intrinsics"] = intrinsics
    sequence = build_dataset({"name": "rgbd_sequence", "root": str(root), **settings})
    members = {frame.number: frame for pair in sequence.pairs for frame in pair}
    chosen = [members[number] for number in sorted(members) if (number - start) % step == 0]
    if len(chosen) < 2:
        raise ValueError(f"{root}: fewer than 2 frames numbered {start}, {start + step}, ... below {stop}")
    out.mkdir(parents=True, exist_ok=True)
    files = []
    for frame in chosen:
        files.append(out / f"scan_{frame.number}.ply")
        write_point_cloud(files[-1], sequence.frame_points(frame).astype("float32"))
    if all(frame.pose is not None for frame in chosen):
        write_conf(out / "poses.conf", {file.name: frame.pose for file, frame in zip(files, chosen, strict=True)})
    return files


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="the RGB-D sequence folder")
    parser.add_argument("out", type=Path, help="the scan folder to write")
    parser.add_argument("--frames", type=int, nargs=3, default=(0, 10**9, 1), metavar=("START", "STOP", "STEP"))
    parser.add_argument("--pixel-stride", type=int, default=2, help="back-project every n-th pixel (2)")
    parser.add_argument("--max-depth", type=float, default=None, help="drop points farther than this (metres)")
    parser.add_argument(
        "--intrinsics",
        type=float,
        nargs=4,
        default=None,
        metavar=("FX", "FY", "CX", "CY"),
        help="pinhole intrinsics in pixels (default: the sequence's own file, else its layout's)",
    )
    args = parser.parse_args(argv)
    try:
        frames = tuple(args.frames)
        files = export_frames(args.root, args.out, frames, args.pixel_stride, args.max_depth, args.intrinsics)
    except (ValueError, FileNotFoundError) as error:
        print(f"export_rgbd_scans: {error}", file=sys.stderr)
        return 2
    labelled = " and poses.conf" if (args.out / "poses.conf").is_file() else ""
    print(f"{len(files)} scans{labelled} in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
