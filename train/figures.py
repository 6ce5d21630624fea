"""Before/after pictures of a registration: 3D scatter plots of source and target.

Left panel: the source (orange) and the target (blue) as given; right panel: the source moved by
the estimated transform ``T`` (``tgt ≈ R @ src + t``) over the same target. Both panels share
their axis limits so that the motion is visible. Figures are built with matplotlib's
object API (no pyplot state), so this module is safe to use from any backend or thread.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

SOURCE_COLOR = "#e66101"
TARGET_COLOR = "#1f78b4"


def _numpy(array: np.ndarray | torch.Tensor, name: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """Float64 numpy copy of ``array`` with a shape check (``None`` = any size)."""
    value = array.detach().cpu().double().numpy() if isinstance(array, torch.Tensor) else np.asarray(array, float)
    if value.ndim != len(shape) or any(s is not None and s != v for s, v in zip(shape, value.shape, strict=True)):
        expected = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name} must have shape {expected}, got {value.shape}")
    return value


def _thin(points: np.ndarray, max_points: int) -> np.ndarray:
    """At most ``max_points`` evenly strided points."""
    if len(points) <= max_points:
        return points
    return points[np.linspace(0, len(points) - 1, max_points).astype(int)]


def registration_figure(
    src: np.ndarray | torch.Tensor,
    tgt: np.ndarray | torch.Tensor,
    T: np.ndarray | torch.Tensor,
    *,
    title: str | None = None,
    max_points: int = 3000,
    point_size: float = 2.0,
) -> Figure:
    """A two-panel figure: before (source, target) and after (``T @ source``, target).

    Args:
        src: array of shape ``(N, 3)`` giving the source points.
        tgt: array of shape ``(M, 3)`` giving the target points.
        T: array of shape ``(4, 4)`` giving the estimated source-to-target transform.
        title: figure title.
        max_points: points drawn per cloud (evenly thinned beyond that).
        point_size: marker size.

    Returns:
        The matplotlib figure (not attached to pyplot).
    """
    src = _thin(_numpy(src, "src", (None, 3)), max_points)
    tgt = _thin(_numpy(tgt, "tgt", (None, 3)), max_points)
    T = _numpy(T, "T", (4, 4))
    moved = src @ T[:3, :3].T + T[:3, 3]
    everything = np.concatenate([src, tgt, moved])
    center = (everything.max(0) + everything.min(0)) / 2
    half = (everything.max(0) - everything.min(0)).max() / 2 * 1.05 or 1.0
    figure = Figure(figsize=(10, 5), layout="constrained")
    FigureCanvasAgg(figure)
    for column, (label, source) in enumerate((("before", src), ("after", moved))):
        axes = figure.add_subplot(1, 2, column + 1, projection="3d")
        axes.scatter(*tgt.T, s=point_size, c=TARGET_COLOR, label="target", depthshade=False)
        axes.scatter(*source.T, s=point_size, c=SOURCE_COLOR, label="source", depthshade=False)
        for axis, c in zip("xyz", center, strict=True):
            getattr(axes, f"set_{axis}lim")(c - half, c + half)
        axes.set_box_aspect((1, 1, 1))
        axes.set_title(label)
        axes.legend(loc="upper right", markerscale=4)
    if title:
        figure.suptitle(title)
    return figure


def plot_registration(
    src: np.ndarray | torch.Tensor,
    tgt: np.ndarray | torch.Tensor,
    T: np.ndarray | torch.Tensor,
    path: str | Path,
    *,
    title: str | None = None,
    max_points: int = 3000,
    dpi: int = 100,
) -> Path:
    """Save the before/after figure of :func:`registration_figure` as a PNG.

    Args:
        src: array of shape ``(N, 3)`` giving the source points.
        tgt: array of shape ``(M, 3)`` giving the target points.
        T: array of shape ``(4, 4)`` giving the estimated source-to-target transform.
        path: output file (folders are created).
        title: figure title.
        max_points: points drawn per cloud.
        dpi: resolution.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    registration_figure(src, tgt, T, title=title, max_points=max_points).savefig(path, dpi=dpi)
    return path
