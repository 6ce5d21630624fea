"""Pairs generated from a collection of complete shapes by a protocol (paper or RPM-Net crop)."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from typing import Any, Protocol

from linereg.datasets.base import PairDataset, item_rng
from linereg.datasets.protocol import CropProtocol, Shape, ShapeViews, ViewProtocol, protocol_settings
from linereg.structures import PairSample

_PAIR_STREAM = 11


class ShapeCollection(Protocol):
    """What a shape source provides: an indexable list of :class:`Shape`."""

    split: str

    def __len__(self) -> int: ...

    def load(self, index: int) -> Shape: ...

    def describe(self) -> dict[str, Any]: ...


class ShapePairDataset(PairDataset):
    """Pairs ``index = shape_index * len(views) + slot`` (view ``views[slot]``) of a shape collection.

    Consecutive indices share a shape, whose renderer (ray-casting scene, whole-surface
    samples) stays in a small per-process LRU cache.

    Args:
        shapes: the shape source.
        protocol: pair protocol (see :mod:`linereg.datasets.protocol`).
        seed: base seed; pair ``index`` uses the generator ``(seed, split, index)``.
        name: registry name recorded in metadata and cache folder names.
        shape_cache_size: renderers kept per process.
        views: the protocol's view indices to use (a held-out-views split); ``None``: all.
    """

    def __init__(
        self,
        shapes: ShapeCollection,
        protocol: ViewProtocol | CropProtocol,
        *,
        seed: int = 0,
        name: str = "shapes",
        shape_cache_size: int = 4,
        views: Sequence[int] | None = None,
    ) -> None:
        if len(shapes) == 0:
            raise ValueError(f"{name}: the shape source is empty ({shapes.describe()})")
        all_views = range(protocol.pairs_per_shape)
        self.views = list(all_views) if views is None else sorted(int(v) for v in views)
        if not self.views or any(v not in all_views for v in self.views):
            raise ValueError(f"{name}: views must be a non-empty subset of 0..{protocol.pairs_per_shape - 1}")
        self.shapes = shapes
        self.protocol = protocol
        self.seed = seed
        self.registry_name = name
        self.shape_cache_size = shape_cache_size
        self._renderers: OrderedDict[int, ShapeViews] = OrderedDict()

    def __len__(self) -> int:
        return len(self.shapes) * len(self.views)

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_renderers"] = OrderedDict()
        return state

    def _renderer(self, shape_index: int) -> ShapeViews:
        """The (cached) renderer of shape ``shape_index``."""
        if shape_index in self._renderers:
            self._renderers.move_to_end(shape_index)
            return self._renderers[shape_index]
        renderer = ShapeViews(self.shapes.load(shape_index))
        self._renderers[shape_index] = renderer
        while len(self._renderers) > self.shape_cache_size:
            self._renderers.popitem(last=False)
        return renderer

    def make_pair(self, index: int) -> PairSample:
        shape_index, slot = divmod(index, len(self.views))
        view = self.views[slot]
        renderer = self._renderer(shape_index)
        split_stream = {"train": 0, "val": 1, "test": 2}.get(self.shapes.split, 3)
        rng = item_rng(self.seed, _PAIR_STREAM, split_stream, shape_index * self.protocol.pairs_per_shape + view)
        pair = self.protocol.make_pair(renderer, view, rng)
        pair.meta = {
            "dataset": self.registry_name,
            "index": index,
            "shape": renderer.shape.name,
            **renderer.shape.meta,
            **pair.meta,
        }
        return pair

    def settings(self) -> dict[str, Any]:
        return {
            "dataset": self.registry_name,
            "shapes": self.shapes.describe(),
            "views": self.views,
            "protocol": protocol_settings(self.protocol),
            "seed": self.seed,
        }
