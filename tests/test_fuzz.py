"""Property-based fuzzing (hypothesis) of every registered loss and every registered model.

Inputs vary in shape, geometry (random, coincident, collinear, planar points), scale (1e-9 to
1e6), dtype (float16/32/64) and padding (``*_lengths``: valid, zero-length samples included, or
negative, above the padded size, fractional or of the wrong size). The
contract under test: either finite values with finite gradients, or a ``ValueError`` /
``TypeError`` whose message names the offending argument. Runs are derandomized, so a failure
reproduces; hypothesis prints the smallest failing case.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass

import pytest
import torch
import torch.nn.functional as F
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import linereg.losses.supervised  # noqa: F401  (registers the supervised losses and regularisers)
from linereg.losses import LOSSES, AlignmentLoss, build_loss
from linereg.losses.lines import SAMPLERS
from linereg.models import MODELS
from linereg.se3 import inverse, se3_exp, transform_points
from linereg.structures import PairBatch, RegistrationOutput

GEOMETRIES = ("random", "coincident", "collinear", "planar")
SCALES = (1e-9, 1e-6, 1e-3, 1.0, 1e3, 1e6)
DTYPES = (torch.float16, torch.float32, torch.float64)
# ``*_lengths``: none, valid (zero-length samples included), or invalid in one way.
PADDINGS = ("none", "valid", "negative", "above", "float", "wrong_size")
INVALID_PADDINGS = PADDINGS[2:]
FUZZ = settings(
    max_examples=12,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)
# A clear error names what was wrong: one of these arguments (or a field of them).
ARGUMENT = re.compile(
    r"\b(batch\.)?(src|tgt|x|y)(_xyz|_normals|_lengths)?\b|\blengths\b|\bgt_transform\b|\btransforms?\b|"
    r"\bextras\b|\bnu0\b|\bdtype\b|\bfloat16\b|\bpoints\b|\blines\b|\bsampling\b|\bvariant\b"
)
SMALL_MODELS = {
    "dcp_v1": {"emb_dims": 16, "k": 4},
    "dcp_v2": {"emb_dims": 16, "k": 4, "ff_dims": 16, "heads": 2},
    "rpmnet": {"feature_dim": 8, "num_neighbors": 4, "train_iters": 1},
    "fmr": {"dim_k": 16, "decoder_points": 8, "train_iters": 2},
}
SUPERVISED_LOSS = {"dcp_v1": "gt_dcp", "dcp_v2": "gt_dcp", "rpmnet": "gt_rpmnet", "fmr": "gt_fmr"}


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@dataclass(frozen=True)
class Case:
    """One fuzzed input: sizes, geometry, scale, dtype, padding and a seed for the values."""

    batch_size: int
    num_src: int
    num_tgt: int
    geometry: str
    scale: float
    dtype: torch.dtype
    padding: str
    seed: int


@st.composite
def cases(draw, *, max_points: int = 24, equal_counts: bool = False, paddings: tuple[str, ...] = PADDINGS) -> Case:
    num_src = draw(st.integers(1, max_points))
    return Case(
        batch_size=draw(st.integers(1, 2)),
        num_src=num_src,
        num_tgt=num_src if equal_counts else draw(st.integers(1, max_points)),
        geometry=draw(st.sampled_from(GEOMETRIES)),
        scale=draw(st.sampled_from(SCALES)),
        dtype=draw(st.sampled_from(DTYPES)),
        padding=draw(st.sampled_from(paddings)),
        seed=draw(st.integers(0, 2**16)),
    )


def make_cloud(case: Case, num_points: int, generator: torch.Generator) -> torch.Tensor:
    """``(B, num_points, 3)`` float64 points of the case's geometry, scaled and offset."""
    shape = (case.batch_size, num_points)
    if case.geometry == "random":
        unit = torch.randn(*shape, 3, generator=generator, dtype=torch.float64)
    elif case.geometry == "coincident":
        unit = torch.randn(case.batch_size, 1, 3, generator=generator, dtype=torch.float64).expand(*shape, 3)
    elif case.geometry == "collinear":
        direction = F.normalize(torch.randn(case.batch_size, 1, 3, generator=generator, dtype=torch.float64), dim=-1)
        unit = torch.randn(*shape, 1, generator=generator, dtype=torch.float64) * direction
    else:
        basis = torch.randn(case.batch_size, 2, 3, generator=generator, dtype=torch.float64)
        unit = torch.randn(*shape, 2, generator=generator, dtype=torch.float64) @ basis
    offset = torch.randn(case.batch_size, 1, 3, generator=generator, dtype=torch.float64)
    return (unit + offset) * case.scale


def make_lengths(case: Case, count: int, generator: torch.Generator) -> torch.Tensor:
    """``*_lengths`` of the case's padding kind for a padded size ``count`` (see :data:`PADDINGS`)."""
    lengths = torch.randint(0, count + 1, (case.batch_size,), generator=generator)
    if case.padding == "negative":
        return lengths - count - 1
    if case.padding == "above":
        return lengths + count + 1
    if case.padding == "float":
        return lengths.double() + 0.5
    if case.padding == "wrong_size":
        return torch.cat([lengths, lengths])
    return lengths


def make_batch(case: Case, *, normals: bool) -> PairBatch:
    """A :class:`PairBatch` of the case in its dtype, with ``*_lengths`` of its padding kind."""
    generator = torch.Generator().manual_seed(case.seed)
    twist = 0.3 * torch.randn(case.batch_size, 6, generator=generator, dtype=torch.float64)
    gt = se3_exp(twist)
    src = make_cloud(case, case.num_src, generator)
    tgt = transform_points(gt, make_cloud(case, case.num_tgt, generator))
    fields = {"src_xyz": src.to(case.dtype), "tgt_xyz": tgt.to(case.dtype), "gt_transform": gt.to(case.dtype)}
    if normals:
        for side, count in (("src", case.num_src), ("tgt", case.num_tgt)):
            direction = torch.randn(case.batch_size, count, 3, generator=generator, dtype=torch.float64)
            fields[f"{side}_normals"] = F.normalize(direction, dim=-1).to(case.dtype)
    if case.padding != "none":
        for side, count in (("src", case.num_src), ("tgt", case.num_tgt)):
            fields[f"{side}_lengths"] = make_lengths(case, count, generator)
    return PairBatch(**fields, meta=[{"index": b} for b in range(case.batch_size)])


def fake_output(batch: PairBatch, generator: torch.Generator) -> tuple[RegistrationOutput, list[torch.Tensor]]:
    """A model-like output with every extra the losses read; returns it and its leaf tensors."""
    dtype, (batch_size, num_src, _), num_tgt = batch.src_xyz.dtype, batch.src_xyz.shape, batch.tgt_xyz.shape[1]
    twists = [
        (0.2 * torch.randn(batch_size, 6, generator=generator, dtype=torch.float64)).requires_grad_() for _ in range(2)
    ]
    transforms = [se3_exp(twist).to(dtype) for twist in twists]
    logits = torch.randn(batch_size, num_src, num_tgt, generator=generator, dtype=torch.float64).requires_grad_()
    perm = torch.softmax(logits, dim=-1).to(dtype) * 0.9
    decoded = torch.randn(batch_size, 8, 3, generator=generator, dtype=torch.float64).requires_grad_()
    extras = {
        "perm_matrices": [perm, perm],
        "transform_reverse": inverse(transforms[-1]),
        "reconstructions": [(batch.tgt_xyz, decoded.to(dtype)), (batch.src_xyz, decoded.to(dtype))],
    }
    return RegistrationOutput(transforms=transforms, extras=extras), [*twists, logits, decoded]


def assert_finite_or_clear_error(run, what: str, *, invalid: bool = False) -> None:
    """``run()`` returns ``(value, leaves)``: value finite and leaf gradients finite, or a clear error.

    With ``invalid`` (the input breaks the contract, e.g. negative lengths) the error is required.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            value, leaves = run()
        except (ValueError, TypeError) as error:
            assert ARGUMENT.search(str(error)), f"{what}: the error does not name an argument: {error!r}"
            return
    assert not invalid, f"{what}: invalid input accepted without an error"
    assert torch.isfinite(value).all(), f"{what}: non-finite value {value}"
    for index, leaf in enumerate(leaves):
        assert leaf.grad is None or torch.isfinite(leaf.grad).all(), f"{what}: non-finite gradient of input {index}"


LOSS_NAMES = LOSSES.names()


def _loss_config(name: str, options: dict) -> dict:
    if name == "line_intersection":
        return {"name": name, "num_lines": 64, "seed": 0, **options}
    return {"name": name}


@pytest.mark.parametrize("name", LOSS_NAMES)
@FUZZ
@given(
    case=cases(),
    options=st.fixed_dictionaries(
        {"variant": st.sampled_from(("paper", "authors", "linereg")), "sampling": st.sampled_from(sorted(SAMPLERS))}
    ),
)
def test_every_loss_is_finite_or_explains(name, case, options):
    loss = build_loss(_loss_config(name, options))
    batch = make_batch(case, normals=False)

    def run():
        output, leaves = fake_output(batch, torch.Generator().manual_seed(case.seed + 1))
        value = loss(output, batch).total
        if value.requires_grad:
            value.backward()
        return value.detach(), leaves

    reads_lengths = issubclass(LOSSES.get(name), AlignmentLoss)
    invalid = reads_lengths and case.padding in INVALID_PADDINGS
    assert_finite_or_clear_error(run, f"loss {name} on {case} with {options}", invalid=invalid)


MODEL_NAMES = MODELS.names()


@pytest.mark.parametrize("name", MODEL_NAMES)
@FUZZ
@given(data=st.data())
def test_every_model_is_finite_or_explains(name, data):
    case = data.draw(cases(max_points=16, equal_counts=name == "fmr"))
    torch.manual_seed(case.seed)
    model = MODELS.build({"name": name, **SMALL_MODELS[name]}).train()
    batch = make_batch(case, normals=True)
    loss = build_loss({"name": SUPERVISED_LOSS[name]})

    def run():
        output = model(batch)
        value = loss(output, batch).total
        value.backward()
        transforms = torch.stack([T.detach() for T in output.transforms])
        assert torch.isfinite(transforms).all(), f"model {name}: non-finite transform on {case}"
        return value.detach(), list(model.parameters())

    assert_finite_or_clear_error(run, f"model {name} on {case}", invalid=case.padding in INVALID_PADDINGS)
