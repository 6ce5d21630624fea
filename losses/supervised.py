"""The backbones' own training losses: supervised (ground truth) and their regularisers.

Supervised losses (``needs_gt=True``; the base class raises a ``ValueError`` when the batch has
no ``gt_transform``):

* ``gt_rpmnet``: RPM-Net's L1 alignment error plus the outlier penalty, per iteration;
* ``gt_dcp``: DCP's rotation/translation MSE, plus an optional cycle-consistency term;
* ``gt_fmr``: FMR's transform error plus an optional encoder-decoder (Chamfer) term.

Unsupervised regularisers (``needs_gt=False``), combined with the line loss in the paper:

* ``rpmnet_outlier``: the outlier penalty alone (the paper's RPM-Net used 10 x this + lines);
* ``dcp_cycle``: the cycle-consistency term alone;
* ``fmr_reconstruction``: FMR's encoder-decoder Chamfer loss alone.

Inputs: the batch tensors a loss reads (``batch.src_xyz``, ``batch.gt_transform``) must be finite
(a ``ValueError`` names the one that is not). Half-precision inputs (float16, bfloat16) are
computed in float32 and give a float32 loss: squared distances overflow float16 from
coordinates of about 256 on (65504 is its largest value), and so would the loss itself.

Convention: ``T_tgt_src`` maps source to target (``tgt ≈ R @ src + t``) for predictions and
ground truth alike. References: Yew & Lee, CVPR 2020 (RPM-Net); Wang & Solomon, ICCV 2019
(DCP); Huang, Mei & Zhang, CVPR 2020 (FMR); and the training code each released with its paper.
"""

from __future__ import annotations

import torch

from linereg.checks import check_points, check_transform
from linereg.se3 import inverse, transform_points
from linereg.structures import LossOutput, PairBatch, RegistrationOutput

from .base import LOSSES, Loss, iteration_weights
from .chamfer import chamfer_distance


def _extra(output: RegistrationOutput, key: str, loss_name: str, producer: str) -> object:
    """``output.extras[key]``, or a ``ValueError`` saying which model produces it."""
    if key not in output.extras:
        raise ValueError(
            f"{loss_name} needs output.extras[{key!r}], which {producer} returns; got extras {sorted(output.extras)}"
        )
    return output.extras[key]


def _at_least_float32(value: torch.Tensor) -> torch.Tensor:
    """``value`` in float32 when its dtype is narrower (float16, bfloat16), else unchanged."""
    return value.float() if value.is_floating_point() and value.dtype.itemsize < 4 else value


def _checked_batch(batch: PairBatch, *clouds: str) -> PairBatch:
    """``batch`` after checking that ``gt_transform`` (when present) and the named clouds are finite.

    Raises:
        ValueError: naming the tensor (``batch.src_xyz``, ``batch.gt_transform``, ...) with NaN or Inf.
    """
    if batch.gt_transform is not None:
        check_transform(batch.gt_transform, "batch.gt_transform")
    for name in clouds:
        check_points(getattr(batch, name), f"batch.{name}", batched=True)
    return batch


def _eye_like(T: torch.Tensor, size: int) -> torch.Tensor:
    """Identity matrices of shape ``(size, size)`` with the dtype and device of ``T``."""
    return torch.eye(size, dtype=T.dtype, device=T.device)


def outlier_penalty(perm: torch.Tensor) -> torch.Tensor:
    """RPM-Net's inlier term ``mean_k(1 - sum_j m_jk) + mean_j(1 - sum_k m_jk)``, batch mean.

    Args:
        perm: tensor of shape ``(B, J, K)`` giving a partial assignment (slack removed).

    Returns:
        Scalar tensor; 0 for a full permutation, up to 2 when nothing is matched.
    """
    unmatched_tgt = (1.0 - perm.sum(dim=1)).mean(dim=1)
    unmatched_src = (1.0 - perm.sum(dim=2)).mean(dim=1)
    return (unmatched_tgt + unmatched_src).mean()


def _discounted_outlier_penalty(output: RegistrationOutput, discount: float, loss_name: str) -> torch.Tensor:
    """Sum over iterations of ``discount ** (n - 1 - i) * outlier_penalty(perm_i)``."""
    perms = _extra(output, "perm_matrices", loss_name, "RPM-Net")
    if len(perms) != len(output.transforms):
        raise ValueError(f"{loss_name}: {len(perms)} perm_matrices for {len(output.transforms)} transforms")
    weights = iteration_weights(len(perms), discount)
    return sum(w * outlier_penalty(_at_least_float32(perm)) for w, perm in zip(weights, perms, strict=True))


@LOSSES.register("gt_rpmnet", needs_gt=True)
class RPMNetSupervisedLoss(Loss):
    """RPM-Net's supervised loss.

    Per iteration ``i`` of ``n``: the mean absolute difference (over points and coordinates)
    between the source moved by the estimate and by the ground truth, plus
    ``outlier_weight * outlier_penalty(perm_i)``, weighted by ``discount ** (n - 1 - i)`` and
    summed.

    Args:
        outlier_weight: weight of the outlier penalty (0.01 in RPM-Net); needs
            ``output.extras["perm_matrices"]`` unless 0.
        discount: per-iteration discount.
    """

    needs_gt = True

    def __init__(self, outlier_weight: float = 0.01, discount: float = 0.5) -> None:
        super().__init__()
        self.outlier_weight = outlier_weight
        self.discount = discount

    def compute(self, output: RegistrationOutput, batch: PairBatch) -> LossOutput:
        src = _at_least_float32(_checked_batch(batch, "src_xyz").src_xyz)
        expected = transform_points(batch.gt_transform.to(src.dtype), src)
        weights = iteration_weights(len(output.transforms), self.discount)
        registration = sum(
            w * (transform_points(T.to(src.dtype), src) - expected).abs().mean()
            for w, T in zip(weights, output.transforms, strict=True)
        )
        terms = {"registration": registration}
        if self.outlier_weight:
            penalty = _discounted_outlier_penalty(output, self.discount, "gt_rpmnet")
            terms["outlier"] = self.outlier_weight * penalty
        return LossOutput(total=sum(terms.values()), terms=terms)


@LOSSES.register("rpmnet_outlier", needs_gt=False)
class RPMNetOutlierLoss(Loss):
    """RPM-Net's outlier penalty alone (no ground truth), discounted over iterations.

    Args:
        discount: per-iteration discount.
    """

    needs_gt = False

    def __init__(self, discount: float = 0.5) -> None:
        super().__init__()
        self.discount = discount

    def compute(self, output: RegistrationOutput, batch: PairBatch) -> LossOutput:
        penalty = _discounted_outlier_penalty(output, self.discount, "rpmnet_outlier")
        return LossOutput(total=penalty, terms={"outlier": penalty})


def cycle_consistency(T_tgt_src: torch.Tensor, T_src_tgt: torch.Tensor) -> torch.Tensor:
    """DCP's cycle term: ``MSE(R_ba R_ab, I) + mean((R_ba t_ab + t_ba)^2)``.

    Both parts are read off ``T_ba @ T_ab``, which is the identity for a consistent pair.
    (DCP's repository, ``main.py``, writes the translation part as ``R_ba^T t_ab + t_ba``, which
    is not zero for a consistent pair unless ``t_ab = 0``; the composition is used here.)

    Args:
        T_tgt_src: tensor of shape ``(B, 4, 4)`` giving the forward estimates ``T_ab``.
        T_src_tgt: tensor of shape ``(B, 4, 4)`` giving the reverse estimates ``T_ba``.

    Returns:
        Scalar tensor.
    """
    round_trip = _at_least_float32(T_src_tgt) @ _at_least_float32(T_tgt_src)
    rotation = (round_trip[:, :3, :3] - _eye_like(round_trip, 3)).square().mean()
    return rotation + round_trip[:, :3, 3].square().mean()


@LOSSES.register("gt_dcp", needs_gt=True)
class DCPSupervisedLoss(Loss):
    """DCP's supervised loss on the final estimate.

    ``MSE(R_pred^T R_gt, I) + MSE(t_pred, t_gt)`` (means over matrix entries, coordinates and
    the batch), plus ``cycle_weight *`` :func:`cycle_consistency` (DCP used 0.1 with
    ``--cycle``), which needs ``output.extras["transform_reverse"]``.

    Args:
        cycle_weight: weight of the cycle term (0 disables it).
    """

    needs_gt = True

    def __init__(self, cycle_weight: float = 0.0) -> None:
        super().__init__()
        self.cycle_weight = cycle_weight

    def compute(self, output: RegistrationOutput, batch: PairBatch) -> LossOutput:
        predicted = _at_least_float32(output.transform)
        gt = _checked_batch(batch).gt_transform.to(predicted.dtype)
        relative = predicted[:, :3, :3].mT @ gt[:, :3, :3]
        terms = {
            "rotation": (relative - _eye_like(relative, 3)).square().mean(),
            "translation": (predicted[:, :3, 3] - gt[:, :3, 3]).square().mean(),
        }
        if self.cycle_weight:
            reverse = _extra(output, "transform_reverse", "gt_dcp", "DCP")
            terms["cycle"] = self.cycle_weight * cycle_consistency(predicted, reverse)
        return LossOutput(total=sum(terms.values()), terms=terms)


@LOSSES.register("dcp_cycle", needs_gt=False)
class DCPCycleLoss(Loss):
    """DCP's cycle-consistency term alone (no ground truth); see :func:`cycle_consistency`."""

    needs_gt = False

    def compute(self, output: RegistrationOutput, batch: PairBatch) -> LossOutput:
        reverse = _extra(output, "transform_reverse", "dcp_cycle", "DCP")
        value = cycle_consistency(output.transform, reverse)
        return LossOutput(total=value, terms={"cycle": value})


def reconstruction_chamfer(output: RegistrationOutput, loss_name: str) -> torch.Tensor:
    """Sum over ``extras["reconstructions"]`` of the batch-mean squared Chamfer distance.

    Half-precision clouds are passed in float32: :func:`chamfer_distance` returns the dtype of
    its input, and squared distances of coordinates above ~256 exceed float16.
    """
    pairs = _extra(output, "reconstructions", loss_name, "FMR (with a decoder)")
    if not pairs:
        raise ValueError(
            f"{loss_name} needs reconstructions, but the model returned none (FMR built with "
            "decoder_points=None has no decoder)"
        )
    return sum(
        chamfer_distance(_at_least_float32(inputs), _at_least_float32(decoded), squared=True).mean()
        for inputs, decoded in pairs
    )


@LOSSES.register("gt_fmr", needs_gt=True)
class FMRSupervisedLoss(Loss):
    """FMR's supervised (or, with the reconstruction term, semi-supervised) loss.

    ``transform_weight * MSE(T_pred @ T_gt^-1, I_4)`` on the final estimate (FMR's
    ``16 * MSE(g . igt, I4)``: the sum of squared entries over the batch size) plus
    ``reconstruction_weight *`` the encoder-decoder squared Chamfer loss (FMR's ``loss_cf``;
    needs ``output.extras["reconstructions"]``).

    Args:
        transform_weight: weight of the transform term.
        reconstruction_weight: weight of the reconstruction term (0 disables it).
    """

    needs_gt = True

    def __init__(self, transform_weight: float = 16.0, reconstruction_weight: float = 1.0) -> None:
        super().__init__()
        self.transform_weight = transform_weight
        self.reconstruction_weight = reconstruction_weight

    def compute(self, output: RegistrationOutput, batch: PairBatch) -> LossOutput:
        predicted = _at_least_float32(output.transform)
        residual = predicted @ inverse(_checked_batch(batch, "src_xyz", "tgt_xyz").gt_transform.to(predicted.dtype))
        transform_error = (residual - _eye_like(residual, 4)).square().mean()
        terms = {"transform": self.transform_weight * transform_error}
        if self.reconstruction_weight:
            chamfer = reconstruction_chamfer(output, "gt_fmr")
            terms["reconstruction"] = self.reconstruction_weight * chamfer
        return LossOutput(total=sum(terms.values()), terms=terms)


@LOSSES.register("fmr_reconstruction", needs_gt=False)
class FMRReconstructionLoss(Loss):
    """FMR's encoder-decoder loss alone: squared Chamfer between each input and its decoding."""

    needs_gt = False

    def compute(self, output: RegistrationOutput, batch: PairBatch) -> LossOutput:
        _checked_batch(batch, "src_xyz", "tgt_xyz")
        value = reconstruction_chamfer(output, "fmr_reconstruction")
        return LossOutput(total=value, terms={"reconstruction": value})
