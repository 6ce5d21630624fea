"""RPM-Net's translation on partial views: the transform head's frame, the centroid
bias of a flat assignment, and the nearest-neighbour translation refinement that removes it."""

from __future__ import annotations

import math

import pytest
import torch

from linereg.models import MODELS
from linereg.models.blocks import refine_translation, soft_correspondence_transform
from linereg.procrustes import procrustes_naive
from linereg.random_poses import random_transform_paper
from linereg.se3 import transform_normals, transform_points
from linereg.structures import PairBatch

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def fibonacci_sphere(count: int) -> torch.Tensor:
    """``(count, 3)`` float64 points spread evenly over the unit sphere."""
    k = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1 - 2 * k / count
    azimuth = math.pi * (1 + 5**0.5) * k
    radius = (1 - z * z).sqrt()
    return torch.stack((radius * azimuth.cos(), radius * azimuth.sin(), z), dim=-1)


def partial_view_of_a_sphere(count: int = 800, seed: int = 0):
    """Source: the z > 0 half of a sphere; target: the whole sphere moved by a known pose.

    Returns ``(src (1, J, 3), tgt (1, K, 3), T_gt (1, 4, 4), front (K,) bool)``, where ``front``
    marks the target points that are the source's points moved.
    """
    sphere = fibonacci_sphere(count)
    front = sphere[:, 2] > 0
    T_gt = random_transform_paper(1, seed, max_angle_deg=45.0, dtype=torch.float64)
    return sphere[front][None], transform_points(T_gt, sphere[None]), T_gt, front


def translation_error(T: torch.Tensor, T_gt: torch.Tensor) -> float:
    return float((T[:, :3, 3] - T_gt[:, :3, 3]).norm(dim=-1).max())


def rotation_error_deg(T: torch.Tensor, T_gt: torch.Tensor) -> float:
    cosine = ((T[:, :3, :3].mT @ T_gt[:, :3, :3]).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    return float(torch.rad2deg(torch.arccos(cosine.clamp(-1, 1))).max())


def naive_refine_translation(src, tgt, T, weights, iterations):
    """One pair at a time, with full distance matrices."""
    refined = []
    for s, t, transform, w in zip(src, tgt, T, weights, strict=True):
        moved = s @ transform[:3, :3].T + transform[:3, 3]
        p = w / w.sum()
        shift = torch.zeros(3, dtype=s.dtype)
        for _ in range(iterations):
            nearest = t[torch.cdist(moved + shift, t).argmin(1)]
            shift = shift + (p[:, None] * (nearest - moved - shift)).sum(0)
        result = transform.clone()
        result[:3, 3] += shift
        refined.append(result)
    return torch.stack(refined)


class TestTransformHeadFrame:
    def test_exact_correspondences_give_the_pose(self):
        """RPM-Net's head, fed the true matches of a partial view (the rest slack), is exact."""
        src, tgt, T_gt, front = partial_view_of_a_sphere()
        assignment = torch.zeros(1, src.shape[1], tgt.shape[1], dtype=torch.float64)
        assignment[0, torch.arange(src.shape[1]), front.nonzero()[:, 0]] = 1.0
        T = soft_correspondence_transform(src, tgt, assignment, weighted=True, model_name="test")
        # Up to RPM-Net's epsilon in the virtual points' denominator (relative 1e-5).
        assert translation_error(T, T_gt) < 1e-4
        assert rotation_error_deg(T, T_gt) < 1e-3
        torch.testing.assert_close(T, procrustes_naive(src, tgt[:, front]), atol=1e-4, rtol=0)

    def test_a_flat_assignment_aligns_centroids(self):
        """The translation floor: a nearly uniform assignment still gives the rotation, but its
        translation is centroid alignment, off by the view's offset from the whole's centroid."""
        src, tgt, T_gt, front = partial_view_of_a_sphere()
        exact = torch.zeros(1, src.shape[1], tgt.shape[1], dtype=torch.float64)
        exact[0, torch.arange(src.shape[1]), front.nonzero()[:, 0]] = 1.0
        flat = 0.99 * torch.full_like(exact, 1.0 / tgt.shape[1]) + 0.01 * exact
        T = soft_correspondence_transform(src, tgt, flat, weighted=True, model_name="test")
        assert rotation_error_deg(T, T_gt) < 1e-3
        centroid_offset = float((tgt.mean(1) - transform_points(T_gt, src.mean(1, keepdim=True))[:, 0]).norm())
        assert centroid_offset == pytest.approx(0.5, abs=0.01)  # a hemispherical shell's centroid: r / 2
        assert translation_error(T, T_gt) == pytest.approx(centroid_offset, rel=0.02)
        refined = refine_translation(src, tgt, T, flat.sum(-1), 60)
        assert translation_error(refined, T_gt) < 1e-3
        torch.testing.assert_close(refined[:, :3, :3], T[:, :3, :3])


class TestRefineTranslation:
    def test_matches_the_naive_loop(self):
        generator = torch.Generator().manual_seed(1)
        src = torch.rand(3, 50, 3, generator=generator, dtype=torch.float64)
        tgt = torch.rand(3, 70, 3, generator=generator, dtype=torch.float64)
        T = random_transform_paper(3, 2, dtype=torch.float64)
        weights = torch.rand(3, 50, generator=generator, dtype=torch.float64)
        for iterations in (1, 4):
            torch.testing.assert_close(
                refine_translation(src, tgt, T, weights, iterations),
                naive_refine_translation(src, tgt, T, weights, iterations),
            )

    def test_zero_iterations_and_zero_weights(self):
        generator = torch.Generator().manual_seed(3)
        src = torch.rand(2, 40, 3, generator=generator)
        tgt = torch.rand(2, 40, 3, generator=generator)
        T = random_transform_paper(2, 4)
        torch.testing.assert_close(refine_translation(src, tgt, T, torch.ones(2, 40), 0), T)
        zero = refine_translation(src, tgt, T, torch.zeros(2, 40), 2)
        torch.testing.assert_close(zero, refine_translation(src, tgt, T, torch.ones(2, 40), 2))

    def test_gradients_reach_the_transform_unrefined(self):
        src, tgt, T_gt, _ = partial_view_of_a_sphere(200)
        T = T_gt.clone().requires_grad_(True)
        refine_translation(src, tgt, T, torch.ones(1, src.shape[1], dtype=torch.float64), 3).sum().backward()
        torch.testing.assert_close(T.grad, torch.ones_like(T))

    @pytest.mark.parametrize(
        ("kwargs", "message"),
        [
            ({"iterations": -1}, "iterations must be >= 0"),
            ({"weights": torch.ones(2, 5)}, r"weights must have shape \(2, 40\)"),
            ({"weights": -torch.ones(2, 40)}, "finite and non-negative"),
            ({"transform": torch.eye(4)}, r"transform must have shape \(2, 4, 4\)"),
        ],
    )
    def test_bad_arguments_are_named(self, kwargs, message):
        arguments = {
            "src": torch.rand(2, 40, 3),
            "tgt": torch.rand(2, 30, 3),
            "transform": torch.eye(4).expand(2, 4, 4),
            "weights": torch.ones(2, 40),
            "iterations": 1,
        }
        with pytest.raises(ValueError, match=message):
            refine_translation(**{**arguments, **kwargs})


class TestRPMNetTranslationRefinement:
    def _pair(self) -> PairBatch:
        generator = torch.Generator().manual_seed(0)
        src = torch.rand(2, 48, 3, generator=generator) - 0.5
        normals = torch.nn.functional.normalize(torch.randn(2, 48, 3, generator=generator), dim=-1)
        T = random_transform_paper(2, 5)
        return PairBatch(src, transform_points(T, src), normals, transform_normals(T, normals), gt_transform=T)

    def test_appends_the_refined_last_estimate_outside_training_only(self):
        batch = self._pair()
        small = {"name": "rpmnet", "feature_dim": 16, "num_neighbors": 8}
        torch.manual_seed(0)
        plain = MODELS.build(small)
        refined_model = MODELS.build({**small, "translation_refinement": 3})
        refined_model.load_state_dict(plain.state_dict())
        with torch.no_grad():
            before = plain.eval()(batch)
            after = refined_model.eval()(batch)
        assert len(after.transforms) == len(before.transforms) + 1
        for earlier, same in zip(before.transforms, after.transforms[:-1], strict=True):
            torch.testing.assert_close(earlier, same)
        mass = before.extras["perm_matrices"][-1].sum(-1)
        expected = refine_translation(batch.src_xyz, batch.tgt_xyz, before.transforms[-1], mass, 3)
        torch.testing.assert_close(after.transforms[-1], expected)
        assert not torch.allclose(after.transforms[-1], before.transforms[-1])
        torch.testing.assert_close(after.transforms[-1][:, :3, :3], before.transforms[-1][:, :3, :3])
        torch.manual_seed(1)
        training = plain.train()(batch).transforms
        torch.manual_seed(1)
        torch.testing.assert_close(refined_model.train()(batch).transforms, training)

    def test_negative_refinement_is_refused(self):
        with pytest.raises(ValueError, match="translation_refinement must be >= 0"):
            MODELS.build({"name": "rpmnet", "translation_refinement": -1})
