"""Feature-metric registration, FMR (Huang, Mei & Zhang, CVPR 2020), with GroupNorm.

A PointNet encoder maps a cloud to a global feature; the transform minimising the feature
difference between the moved source and the target is found by an inverse-compositional
Lucas-Kanade solver (the original: XiaoshuiHuang/fmr, ``model.py``; the paper's repository,
Dengzhi-USTC/A-robust-registration-loss, ``code/exps_deep_learning/fmr/model.py``, replaces
BatchNorm by GroupNorm with 8 groups):

1. both clouds are zero-meaned; ``f0 = E(target)``;
2. the feature Jacobian at the target comes from finite differences: for each twist direction
   ``e_k`` (``(omega, v)`` order), ``J[:, k] = (f0 - E(exp(-dt_k e_k) target)) / dt_k``, with the
   steps ``dt`` a learnable ``nn.Parameter`` (initialised to 0.01, as in the original);
3. each iteration solves ``dx = -(J^T J + lambda I)^-1 J^T (E(g source) - f0)`` (float64, with
   a tiny damping ``lambda`` so that a rank-deficient Jacobian stays finite) and updates
   ``g <- exp(dx) g``; it stops early once every sample's ``|dx| < tolerance``;
4. the centring is undone: ``T = Trans(mean_tgt) g Trans(-mean_src)``.

The features are computed in the model's precision on every device: autocast is switched off, and cuDNN's
TF32 convolutions (PyTorch's default on Ampere and newer GPUs) too, since their 10-bit mantissa
swamps the finite differences of step 2 (on an H200, FMR with TF32 drifted from the CPU result by
up to 0.32 in the transform's entries).

A decoder (fully connected, ``tanh`` output times ``decoder_scale``) reconstructs each
centred cloud from its feature, for FMR's unsupervised encoder-decoder (Chamfer) loss. Source
and target need the same number of points.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import nn

from linereg.models.base import MODELS
from linereg.se3 import rt_to_matrix, se3_exp, transform_points
from linereg.structures import PairBatch, RegistrationOutput

from .blocks import NormKind, check_norm_kind, check_pair_batch, resolve_groups, shared_mlp

ENCODER_WIDTHS = (64, 64, 64, 128)
ENCODER_GROUPS = (8, 8, 8, 8, 8)
DECODER_WIDTHS = (1024, 512, 256)
DECODER_GROUPS = (8, 8, 8)
# Relative damping of J^T J and the eigenvalue ratio below which a sample is reported.
_DAMPING = 1e-6
_RANK_RTOL = 1e-10


class PointNetEncoder(nn.Module):
    """Shared MLP ``3 -> 64 -> 64 -> 64 -> 128 -> dim_k`` and a global max pool."""

    def __init__(self, dim_k: int, norm: NormKind, groups: tuple[int, ...]) -> None:
        super().__init__()
        self.mlp = shared_mlp(3, [*ENCODER_WIDTHS, dim_k], norm=norm, groups=groups)

    def forward(self, xyz: torch.Tensor) -> torch.Tensor:
        """Global features ``(B, dim_k)`` of clouds ``(B, N, 3)``."""
        return self.mlp(xyz.transpose(1, 2)).amax(dim=-1)


class PointDecoder(nn.Module):
    """Fully connected ``dim_k -> 1024 -> 512 -> 256 -> 3 P`` with ``scale * tanh`` output."""

    def __init__(self, dim_k: int, num_points: int, scale: float, norm: NormKind, groups: tuple[int, ...]) -> None:
        super().__init__()
        self.num_points = num_points
        self.scale = scale
        self.mlp = nn.Sequential(
            shared_mlp(dim_k, DECODER_WIDTHS, norm=norm, groups=groups, layer="linear"),
            nn.Linear(DECODER_WIDTHS[-1], 3 * num_points),
        )

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """Decoded clouds ``(B, P, 3)`` from features ``(B, dim_k)``."""
        decoded = self.scale * torch.tanh(self.mlp(features))
        return decoded.reshape(features.shape[0], self.num_points, 3)


def _translation(offset: torch.Tensor) -> torch.Tensor:
    """Pure translations ``(B, 4, 4)`` by ``offset (B, 3)``."""
    eye = torch.eye(3, dtype=offset.dtype, device=offset.device).expand(offset.shape[0], 3, 3)
    return rt_to_matrix(eye, offset)


@contextmanager
def _full_precision_features(device: torch.device) -> Iterator[None]:
    """The model's own precision inside: no autocast on ``device`` and no TF32 in cuDNN convolutions."""
    cudnn = torch.backends.cudnn
    flags = {
        "enabled": cudnn.enabled,
        "benchmark": cudnn.benchmark,
        "benchmark_limit": cudnn.benchmark_limit,
        "deterministic": cudnn.deterministic,
    }
    with torch.autocast(device.type, enabled=False), cudnn.flags(**flags, allow_tf32=False):
        yield


class FMR(nn.Module):
    """Feature-metric registration.

    Args:
        dim_k: global feature width.
        train_iters: maximum solver iterations in training mode (the FMR paper: 10; the line-loss
            paper's repository trained with 5).
        test_iters: maximum solver iterations in evaluation mode.
        decoder_points: points ``P`` produced by the decoder, or ``None`` for no decoder
            (then ``extras["reconstructions"]`` is empty).
        decoder_scale: the decoder's output range (1 in FMR; the paper repository used 10).
        dt_init: initial finite-difference step of each twist component.
        tolerance: the solver stops once every sample's update norm is below it.
        norm: ``"group"`` (paper repository), ``"batch"`` (original FMR: the encoder is switched
            to evaluation mode for the solver iterations) or ``"none"``.
        groups: one GroupNorm group count for every layer, or ``None`` for the paper
            repository's (8 everywhere).

    ``forward(batch)`` needs equal source and target point counts and returns a
    :class:`RegistrationOutput` with one ``(B, 4, 4)`` source -> target estimate per solver
    iteration (the caller picks one: :func:`linereg.registration.iterates.select_iterate`) and
    ``extras``:

    * ``"reconstructions"``: list of ``(input (B, N, 3), decoded (B, P, 3))`` pairs, for the
      centred target and the centred source;
    * ``"feature_residual"``: ``(B, dim_k)`` feature difference ``E(g source) - f0`` at the last
      iteration's starting estimate.
    """

    def __init__(
        self,
        *,
        dim_k: int = 1024,
        train_iters: int = 10,
        test_iters: int = 10,
        decoder_points: int | None = 1024,
        decoder_scale: float = 1.0,
        dt_init: float = 0.01,
        tolerance: float = 1e-7,
        norm: NormKind = "group",
        groups: int | None = None,
    ) -> None:
        super().__init__()
        check_norm_kind(norm)
        if train_iters < 1 or test_iters < 1:
            raise ValueError(f"train_iters and test_iters must be >= 1, got {train_iters} and {test_iters}")
        self.encoder = PointNetEncoder(dim_k, norm, resolve_groups(ENCODER_GROUPS, groups))
        self.decoder = (
            None
            if decoder_points is None
            else PointDecoder(dim_k, decoder_points, decoder_scale, norm, resolve_groups(DECODER_GROUPS, groups))
        )
        self.dt = nn.Parameter(torch.full((6,), float(dt_init)))
        self.train_iters = train_iters
        self.test_iters = test_iters
        self.tolerance = tolerance
        self.freeze_encoder_statistics = norm == "batch"

    def _feature_jacobian(self, template: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """Finite-difference Jacobian ``(B, dim_k, 6)`` of the features at ``template``."""
        batch, num_points, _ = template.shape
        perturbations = se3_exp(torch.diag_embed(-self.dt).to(template.dtype))
        moved = transform_points(perturbations[None], template[:, None])
        perturbed = self.encoder(moved.reshape(batch * 6, num_points, 3)).reshape(batch, 6, -1)
        return ((features[:, None] - perturbed) / self.dt[None, :, None]).transpose(1, 2)

    def _gauss_newton_solver(self, jacobian: torch.Tensor) -> torch.Tensor:
        """The damped pseudo-inverse ``(B, 6, dim_k)`` of ``jacobian``, reporting rank loss."""
        jacobian64 = jacobian.double()
        normal = jacobian64.mT @ jacobian64
        with torch.no_grad():
            eigenvalues = torch.linalg.eigvalsh(normal)
            deficient = eigenvalues[:, 0] <= _RANK_RTOL * eigenvalues[:, -1].clamp_min(1e-300)
            failed = deficient.nonzero().flatten().tolist()
        if failed:
            warnings.warn(
                f"FMR: the feature Jacobian is rank-deficient for batch index(es) {failed} "
                "(features insensitive to some motions, e.g. coincident points); the update "
                "is damped",
                stacklevel=3,
            )
        trace = normal.diagonal(dim1=-2, dim2=-1).sum(-1)
        damping = (_DAMPING * trace / 6 + 1e-12)[:, None, None] * torch.eye(6, dtype=normal.dtype, device=normal.device)
        return torch.linalg.solve(normal + damping, jacobian64.mT).to(jacobian.dtype)

    def _solve(
        self, src: torch.Tensor, tgt_features: torch.Tensor, solver: torch.Tensor, iterations: int
    ) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor]:
        """Inverse-compositional iterations on centred clouds.

        Returns the estimates ``g`` ``(B, 4, 4)`` after each iteration, the source features at
        the start and the feature residual ``(B, dim_k)`` at the start of the last iteration.
        """
        g = torch.eye(4, dtype=src.dtype, device=src.device).expand(src.shape[0], 4, 4)
        estimates: list[torch.Tensor] = []
        first_features: torch.Tensor | None = None
        for _ in range(iterations):
            features = self.encoder(transform_points(g, src))
            if first_features is None:
                first_features = features
            residual = features - tgt_features
            update = -(solver @ residual[..., None])[..., 0]
            g = se3_exp(update) @ g
            estimates.append(g)
            if bool((update.norm(dim=-1) < self.tolerance).all()):
                break
        return estimates, first_features, residual

    def forward(self, batch: PairBatch) -> RegistrationOutput:
        check_pair_batch(batch, "FMR", equal_counts=True, dtype=self.dt.dtype)
        with _full_precision_features(batch.src_xyz.device):
            return self._register(batch)

    def _register(self, batch: PairBatch) -> RegistrationOutput:
        src, tgt = batch.src_xyz, batch.tgt_xyz
        src_mean, tgt_mean = src.mean(dim=1), tgt.mean(dim=1)
        src_centred, tgt_centred = src - src_mean[:, None], tgt - tgt_mean[:, None]
        tgt_features = self.encoder(tgt_centred)
        solver = self._gauss_newton_solver(self._feature_jacobian(tgt_centred, tgt_features))
        uncentre = _translation(tgt_mean)
        centre = _translation(-src_mean)

        iterations = self.train_iters if self.training else self.test_iters
        restore_training = self.freeze_encoder_statistics and self.encoder.training
        if restore_training:
            self.encoder.eval()
        try:
            transforms, first_src_features, residual = self._solve(src_centred, tgt_features, solver, iterations)
        finally:
            if restore_training:
                self.encoder.train()
        transforms = [uncentre @ g @ centre for g in transforms]
        reconstructions = []
        if self.decoder is not None:
            reconstructions = [
                (tgt_centred, self.decoder(tgt_features)),
                (src_centred, self.decoder(first_src_features)),
            ]
        extras = {"reconstructions": reconstructions, "feature_residual": residual}
        return RegistrationOutput(transforms=transforms, extras=extras)


# The paper's defaults are the constructor's: the class itself is the builder.
MODELS.register("fmr")(FMR)
