"""Tests for models/: registry, contracts, numerics and learning, parametrised over MODELS."""

from __future__ import annotations

import warnings

import pytest
import torch
import torch.nn.functional as F

import linereg.losses.supervised  # noqa: F401  (registers the supervised losses)
from linereg.checks import check_transform
from linereg.losses.base import build_loss
from linereg.models import MODELS
from linereg.models.blocks import shared_mlp, soft_correspondence_transform
from linereg.models.rpmnet import PPFFeatures, ball_query, log_sinkhorn
from linereg.random_poses import random_transform_paper
from linereg.se3 import inverse, rotation_angle, rt_to_matrix, transform_normals, transform_points
from linereg.structures import PairBatch, RegistrationOutput

MODEL_NAMES = MODELS.names()

# Small widths keep the suite fast; the architectures are otherwise the published ones.
SMALL = {
    "dcp_v1": {"emb_dims": 32, "k": 8},
    "dcp_v2": {"emb_dims": 32, "k": 8, "ff_dims": 64},
    "rpmnet": {"feature_dim": 16, "num_neighbors": 8},
    "fmr": {"dim_k": 64, "decoder_points": 64},
}
SUPERVISED_LOSS = {
    "dcp_v1": {"name": "gt_dcp"},
    "dcp_v2": {"name": "gt_dcp"},
    "rpmnet": {"name": "gt_rpmnet"},
    "fmr": {"name": "gt_fmr"},
}


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def make_pair(
    batch_size: int = 2,
    num_src: int = 64,
    num_tgt: int | None = None,
    *,
    seed: int = 0,
    max_angle_deg: float = 45.0,
) -> PairBatch:
    """Random clouds with random unit normals; the target is the moved, shuffled source.

    With ``num_tgt`` different from ``num_src`` the target is an independent random cloud.
    """
    generator = torch.Generator().manual_seed(seed)
    src = torch.rand(batch_size, num_src, 3, generator=generator) - 0.5
    src_normals = F.normalize(torch.randn(batch_size, num_src, 3, generator=generator), dim=-1)
    T = random_transform_paper(batch_size, seed, max_angle_deg=max_angle_deg)
    if num_tgt is None or num_tgt == num_src:
        order = torch.randperm(num_src, generator=generator)
        tgt = transform_points(T, src)[:, order]
        tgt_normals = transform_normals(T, src_normals)[:, order]
    else:
        tgt = transform_points(T, torch.rand(batch_size, num_tgt, 3, generator=generator) - 0.5)
        tgt_normals = F.normalize(torch.randn(batch_size, num_tgt, 3, generator=generator), dim=-1)
    return PairBatch(src, tgt, src_normals, tgt_normals, gt_transform=T)


def small_model(name: str, **overrides) -> torch.nn.Module:
    return MODELS.build({"name": name, **SMALL[name], **overrides})


def rotation_error_deg(T_pred: torch.Tensor, T_gt: torch.Tensor) -> torch.Tensor:
    return torch.rad2deg(rotation_angle(T_pred[:, :3, :3].mT @ T_gt[:, :3, :3]))


class TestRegistry:
    def test_registered_names(self):
        assert MODEL_NAMES == ["dcp_v1", "dcp_v2", "fmr", "rpmnet"]
        assert MODELS.names("dcp*") == ["dcp_v1", "dcp_v2"]

    def test_unknown_name_lists_the_models(self):
        with pytest.raises(KeyError, match="dcp_v1, dcp_v2, fmr, rpmnet"):
            MODELS.build({"name": "pointnetlk"})
        with pytest.raises(KeyError, match="needs a 'name'"):
            MODELS.build({"emb_dims": 8})

    def test_unknown_argument_names_the_model(self):
        expected = r"model 'rpmnet' got unknown argument\(s\) \['emb_dims'\]"
        with pytest.raises(TypeError, match=expected):
            MODELS.build({"name": "rpmnet", "emb_dims": 8})

    def test_defaults_are_the_papers(self):
        rpmnet = MODELS.build({"name": "rpmnet"})
        assert (rpmnet.features.radius, rpmnet.features.num_neighbors) == (0.3, 64)
        assert (rpmnet.train_iters, rpmnet.test_iters, rpmnet.sinkhorn_iters) == (2, 5, 5)
        assert [m.num_groups for m in rpmnet.features.prepool_norms] == [8, 8, 8]
        fmr = MODELS.build({"name": "fmr"})
        assert fmr.encoder.mlp[-3].out_channels == 1024
        assert (fmr.train_iters, fmr.test_iters) == (10, 10)
        assert isinstance(fmr.dt, torch.nn.Parameter)
        torch.testing.assert_close(fmr.dt.detach(), torch.full((6,), 0.01))
        dcp = MODELS.build({"name": "dcp_v2"})
        assert (dcp.emb_dims, dcp.embedding.k) == (512, 20)
        groups = [m.num_groups for m in dcp.modules() if isinstance(m, torch.nn.GroupNorm)]
        assert groups == [8, 8, 8, 16, 16]

    def test_norm_variants(self):
        batch = make_pair(2, 48)
        for name, norm in (("dcp_v1", "batch"), ("dcp_v1", "none"), ("fmr", "batch")):
            model = small_model(name, norm=norm)
            assert not any(isinstance(m, torch.nn.GroupNorm) for m in model.modules())
            assert torch.isfinite(model(batch).transform).all()
        with pytest.raises(ValueError, match="RPM-Net supports norm 'group' or 'none'"):
            small_model("rpmnet", norm="batch")
        with pytest.raises(ValueError, match="norm must be one of"):
            small_model("dcp_v2", norm="layer")

    def test_shared_mlp_checks_group_counts(self):
        with pytest.raises(ValueError, match="groups needs one entry per layer"):
            shared_mlp(3, [8, 8], norm="group", groups=[4])
        with pytest.raises(ValueError, match=r"GroupNorm groups \(3\) must divide"):
            shared_mlp(3, [8], norm="group", groups=[3])


def _expected_iterations(name: str, model: torch.nn.Module) -> int:
    if name == "rpmnet":
        return model.train_iters if model.training else model.test_iters
    return 1 if name.startswith("dcp") else -1


@pytest.mark.parametrize("name", MODEL_NAMES)
class TestContract:
    @pytest.mark.parametrize("batch_size", [1, 4])
    def test_output_shapes_and_rigidity(self, name, batch_size):
        model = small_model(name).eval()
        batch = make_pair(batch_size, 64)
        output = model(batch)
        assert isinstance(output, RegistrationOutput)
        expected = _expected_iterations(name, model)
        if expected > 0:
            assert len(output.transforms) == expected
        for T in output.transforms:
            assert T.shape == (batch_size, 4, 4) and T.dtype == torch.float32
            check_transform(T, "transform", rigid_atol=1e-4)
        extras = output.extras
        if name.startswith("dcp"):
            assert extras["transform_reverse"].shape == (batch_size, 4, 4)
            assert extras["scores"].shape == (batch_size, 64, 64)
            torch.testing.assert_close(extras["scores"].sum(-1), torch.ones(batch_size, 64))
        elif name == "rpmnet":
            assert [p.shape for p in extras["perm_matrices"]] == [(batch_size, 64, 64)] * 5
            assert [b.shape for b in extras["beta"] + extras["alpha"]] == [(batch_size,)] * 10
        else:
            shapes = [(a.shape, b.shape) for a, b in extras["reconstructions"]]
            assert shapes == [((batch_size, 64, 3), (batch_size, 64, 3))] * 2

    def test_different_point_counts(self, name):
        model = small_model(name).train()
        batch = make_pair(2, 72, 56)
        if name == "fmr":
            with pytest.raises(ValueError, match="needs equal source and target point counts"):
                model(batch)
            return
        output = model(batch)
        key = "scores" if name.startswith("dcp") else "perm_matrices"
        matrices = output.extras[key]
        assert (matrices if torch.is_tensor(matrices) else matrices[-1]).shape == (2, 72, 56)
        check_transform(output.transform, rigid_atol=1e-4)

    @pytest.mark.parametrize("lengths", [[48, 40], [48, 49], [48, -1], [48.0, 48.0], [48, 48, 48]], ids=str)
    def test_ragged_or_invalid_lengths_are_refused(self, name, lengths):
        batch = make_pair(2, 48)
        batch.src_lengths = torch.tensor(lengths)
        with pytest.raises(ValueError, match=r"needs full clouds: batch\.src_lengths must be None or 48"):
            small_model(name)(batch)

    def test_other_dtypes_are_named(self, name):
        batch = make_pair(1, 16)
        batch.src_xyz = batch.src_xyz.double()
        with pytest.raises(TypeError, match=r"parameters are torch\.float32 but batch\.src_xyz is torch\.float64"):
            small_model(name)(batch)

    def test_one_point_is_refused(self, name):
        batch = make_pair(1, 1)
        with pytest.raises(ValueError, match=r"batch\.src_xyz must hold at least 2 point\(s\), got 1"):
            small_model(name)(batch)

    @pytest.mark.parametrize("init_seed", [0, 1, 2])
    def test_permutation_invariance(self, name, init_seed):
        # In float64: in float32, GroupNorm's sums change with the point order by ~1e-7, and
        # FMR's Gauss-Newton steps amplify that to 2-4e-4 for some initialisations.
        torch.manual_seed(init_seed)
        model = small_model(name).eval().double()
        batch = make_pair(2, 64, seed=3)
        batch = PairBatch(*(t.double() for t in (batch.src_xyz, batch.tgt_xyz, batch.src_normals, batch.tgt_normals)))
        shuffled = PairBatch(
            batch.src_xyz.flip(1),
            batch.tgt_xyz.roll(5, dims=1),
            batch.src_normals.flip(1),
            batch.tgt_normals.roll(5, dims=1),
        )
        torch.testing.assert_close(model(shuffled).transform, model(batch).transform, atol=1e-9, rtol=0)

    def test_gradients_reach_every_parameter(self, name):
        model = small_model(name).train()
        batch = make_pair(2, 64)
        loss = build_loss(SUPERVISED_LOSS[name])(model(batch), batch)
        loss.total.backward()
        missing = [n for n, p in model.named_parameters() if p.grad is None]
        assert not missing
        for parameter_name, parameter in model.named_parameters():
            assert torch.isfinite(parameter.grad).all(), parameter_name
            assert parameter.grad.abs().sum() > 0, parameter_name

    def test_deterministic_with_a_seed(self, name):
        batch = make_pair(2, 48)
        outputs = []
        for _ in range(2):
            torch.manual_seed(7)
            outputs.append(small_model(name).eval()(batch).transforms)
        assert all(torch.equal(a, b) for a, b in zip(*outputs, strict=True))

    def test_coincident_points_stay_finite(self, name):
        batch = make_pair(2, 32)
        point = torch.tensor([0.1, -0.2, 0.3])
        batch.src_xyz = point.expand(2, 32, 3).clone()
        batch.tgt_xyz = point.expand(2, 32, 3).clone()
        batch.src_normals = batch.tgt_normals = F.normalize(torch.ones(2, 32, 3), dim=-1)
        model = small_model(name).train()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            output = model(batch)
        assert any("batch index(es) [0, 1]" in str(w.message) for w in caught)
        assert all(torch.isfinite(T).all() for T in output.transforms)
        build_loss(SUPERVISED_LOSS[name])(output, batch).total.backward()
        for parameter_name, parameter in model.named_parameters():
            assert parameter.grad is None or torch.isfinite(parameter.grad).all(), parameter_name


class TestConsistency:
    @pytest.mark.parametrize("weighted", [False, True])
    def test_rigid_head_is_equivariant(self, weighted):
        """Rotating the target by Q turns the estimate T into Q T (same soft assignment)."""
        batch = make_pair(3, 40, 30, seed=5)
        assignment = torch.rand(3, 40, 30)
        if not weighted:
            assignment = assignment / assignment.sum(-1, keepdim=True)
        Q = random_transform_paper(3, 9, max_angle_deg=90.0)
        estimate = soft_correspondence_transform(
            batch.src_xyz, batch.tgt_xyz, assignment, weighted=weighted, model_name="test"
        )
        moved = soft_correspondence_transform(
            batch.src_xyz,
            transform_points(Q, batch.tgt_xyz),
            assignment,
            weighted=weighted,
            model_name="test",
        )
        torch.testing.assert_close(moved, Q @ estimate, atol=1e-5, rtol=0)

    def test_dcp_reverse_transform(self):
        batch = make_pair(2, 48)
        output = small_model("dcp_v2").eval()(batch)
        torch.testing.assert_close(output.extras["transform_reverse"], inverse(output.transform))
        same = PairBatch(batch.src_xyz, batch.src_xyz.clone())
        cyclic = small_model("dcp_v1", cycle=True).eval()(same)
        torch.testing.assert_close(cyclic.extras["transform_reverse"], cyclic.transform, atol=1e-5, rtol=0)

    def test_rpmnet_transforms_follow_from_reported_matches(self):
        batch = make_pair(2, 64)
        output = small_model("rpmnet").eval()(batch)
        for T, perm in zip(output.transforms, output.extras["perm_matrices"], strict=True):
            refit = soft_correspondence_transform(batch.src_xyz, batch.tgt_xyz, perm, weighted=True, model_name="test")
            torch.testing.assert_close(T, refit)
            assert (perm >= 0).all() and (perm.sum(1) <= 1 + 1e-5).all()
            assert (perm.sum(2) <= 1 + 1e-5).all()

    def test_fmr_recovers_a_pure_translation_exactly(self):
        """Centring makes FMR exact for translations, whatever its weights."""
        batch = make_pair(2, 64)
        offset = torch.tensor([[0.3, -0.1, 0.2], [-0.4, 0.05, 0.0]])
        target = batch.src_xyz.roll(7, dims=1) + offset[:, None]
        output = small_model("fmr").eval()(PairBatch(batch.src_xyz, target))
        expected = rt_to_matrix(torch.eye(3).expand(2, 3, 3), offset)
        torch.testing.assert_close(output.transform, expected, atol=1e-5, rtol=0)

    def test_iteration_counts_follow_training_mode(self):
        batch = make_pair(1, 48)
        rpmnet = small_model("rpmnet", train_iters=3, test_iters=4)
        assert len(rpmnet.train()(batch).transforms) == 3
        assert len(rpmnet.eval()(batch).transforms) == 4
        fmr = small_model("fmr", train_iters=2, test_iters=6, tolerance=0.0)
        assert len(fmr.train()(batch).transforms) == 2
        assert len(fmr.eval()(batch).transforms) == 6

    def test_rpmnet_needs_normals(self):
        batch = make_pair(1, 32)
        batch.tgt_normals = None
        with pytest.raises(ValueError, match=r"RPM-Net needs normals.*Open3D"):
            small_model("rpmnet")(batch)

    @pytest.mark.parametrize("side", ["src", "tgt"])
    @pytest.mark.parametrize("bad", [float("nan"), float("inf")])
    def test_rpmnet_refuses_non_finite_normals(self, side, bad):
        batch = make_pair(1, 32)
        getattr(batch, f"{side}_normals")[0, 5, 1] = bad
        with pytest.raises(ValueError, match=rf"batch\.{side}_normals contains NaN or Inf"):
            small_model("rpmnet")(batch)

    def test_non_finite_assignment_is_not_blamed_on_the_geometry(self):
        src = torch.rand(2, 16, 3)
        assignment = torch.rand(2, 16, 16)
        assignment[1, 3, 4] = float("nan")
        with pytest.warns(UserWarning, match=r"soft assignment is NaN/Inf for batch index\(es\) \[1\]") as caught:
            soft_correspondence_transform(src, src, assignment, weighted=True, model_name="RPM-Net")
        assert not any("collinear" in str(w.message) for w in caught)


def _cuda_and_cpu_transforms(name: str) -> tuple[torch.Tensor, torch.Tensor]:
    torch.manual_seed(0)
    model = small_model(name).eval()
    batch = make_pair(2, 64)
    expected = model(batch).transform
    return model.to("cuda")(batch.to("cuda")).transform.cpu(), expected


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("name", MODEL_NAMES)
def test_cuda_matches_cpu(name):
    """The same arithmetic on both devices: float32 convolutions on the GPU (TF32 off)."""
    with torch.backends.cudnn.flags(enabled=True, allow_tf32=False):
        actual, expected = _cuda_and_cpu_transforms(name)
    torch.testing.assert_close(actual, expected, atol=1e-3, rtol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_fmr_on_cuda_matches_cpu_with_tf32_allowed():
    """FMR switches TF32 off for its features itself: with it on (an H200: 0.32 apart before)."""
    with torch.backends.cudnn.flags(enabled=True, allow_tf32=True):
        actual, expected = _cuda_and_cpu_transforms("fmr")
    torch.testing.assert_close(actual, expected, atol=1e-3, rtol=0)


def test_fmr_features_are_float32_under_autocast_and_tf32():
    """The CPU twin of the test above: inside FMR, autocast and TF32 convolutions are off."""
    model = small_model("fmr").eval()
    seen = []
    model.encoder.register_forward_hook(
        lambda _module, _inputs, output: seen.append(
            (torch.backends.cudnn.allow_tf32, torch.is_autocast_enabled("cpu"), output.dtype)
        )
    )
    with torch.backends.cudnn.flags(enabled=True, allow_tf32=True), torch.autocast("cpu", dtype=torch.bfloat16):
        output = model(make_pair(2, 32))
        assert torch.backends.cudnn.allow_tf32 and torch.is_autocast_enabled("cpu")  # restored
    assert seen and set(seen) == {(False, False, torch.float32)}
    assert output.transform.dtype == torch.float32


class TestRPMNetParts:
    def test_ball_query(self):
        xyz = torch.tensor([[[0.0, 0, 0], [0.1, 0, 0], [0.25, 0, 0], [1.0, 0, 0]]])
        neighbours = ball_query(xyz, radius=0.2, num_neighbors=3)
        assert neighbours.tolist() == [[[0, 1, 0], [1, 0, 2], [2, 1, 2], [3, 3, 3]]]

    @pytest.mark.parametrize("norm", ["group", "none"])
    def test_chunked_features_match_whole(self, norm):
        torch.manual_seed(0)
        features = PPFFeatures(16, 0.3, 12, norm, 8, chunk_bytes=4096)
        batch = make_pair(2, 96)
        whole = features.train()(batch.src_xyz, batch.src_normals)
        with torch.no_grad():
            chunked = features.eval()(batch.src_xyz, batch.src_normals)
        torch.testing.assert_close(chunked, whole, atol=2e-5, rtol=0)

    def test_checkpointing_changes_memory_not_results(self):
        batch = make_pair(2, 64)
        results = []
        for checkpoint in (False, True):
            torch.manual_seed(0)
            model = small_model("rpmnet", checkpoint=checkpoint).train()
            output = model(batch)
            build_loss(SUPERVISED_LOSS["rpmnet"])(output, batch).total.backward()
            results.append((output.transform, model.features.prepool[0].weight.grad))
        for plain, recomputed in zip(*results, strict=True):
            torch.testing.assert_close(recomputed, plain)

    def test_sinkhorn(self):
        log_affinity = torch.randn(2, 5, 7)
        with_slack = log_sinkhorn(log_affinity, 20).exp()
        assert with_slack.shape == (2, 5, 7)
        assert (with_slack.sum(1) <= 1 + 1e-5).all() and (with_slack.sum(2) <= 1 + 1e-5).all()
        square = log_sinkhorn(torch.randn(2, 6, 6), 200, slack=False).exp()
        torch.testing.assert_close(square.sum(1), torch.ones(2, 6), atol=1e-4, rtol=0)
        torch.testing.assert_close(square.sum(2), torch.ones(2, 6), atol=1e-4, rtol=0)


# (model kwargs, loss config, learning rate, maximum steps, maximum Euler angle in degrees)
OVERFIT = {
    "dcp_v1": ({"emb_dims": 64, "k": 10}, {"name": "gt_dcp"}, 1e-3, 80, 45.0),
    "dcp_v2": ({"emb_dims": 64, "k": 10, "ff_dims": 128}, {"name": "gt_dcp"}, 1e-3, 80, 45.0),
    "rpmnet": ({"feature_dim": 32, "num_neighbors": 16}, {"name": "gt_rpmnet"}, 1e-3, 60, 45.0),
    "fmr": (
        {"dim_k": 128, "decoder_points": 128},
        {"name": "gt_fmr", "reconstruction_weight": 0.0},
        1e-3,
        80,
        90.0,
    ),
}


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_overfits_a_single_pair(name):
    """Each model learns one noise-free pair to a rotation error below 1 degree."""
    kwargs, loss_config, lr, max_steps, max_angle = OVERFIT[name]
    torch.manual_seed(0)
    model = MODELS.build({"name": name, **kwargs})
    loss = build_loss(loss_config)
    batch = make_pair(1, 128, seed=2, max_angle_deg=max_angle)
    optimiser = torch.optim.Adam(model.parameters(), lr=lr)
    with torch.no_grad():
        initial = rotation_error_deg(model.eval()(batch).transform, batch.gt_transform).item()
    errors = []
    for step in range(max_steps):
        model.train()
        optimiser.zero_grad()
        loss(model(batch), batch).total.backward()
        optimiser.step()
        if step % 5 == 4:
            with torch.no_grad(), warnings.catch_warnings():
                warnings.simplefilter("error")
                estimate = model.eval()(batch).transform
            errors.append(rotation_error_deg(estimate, batch.gt_transform).item())
            if errors[-1] < 1.0:
                break
    assert initial > 2.0, "the pair is too easy to show learning"
    assert errors[-1] < 1.0, f"rotation error after training: {errors}"


class TestIteratesAreReturnedUntouched:
    """RPM-Net and FMR return every iterate; :func:`select_iterate` picks one without changing them."""

    def _rpmnet_pair(self) -> PairBatch:
        """Small motions (2 deg), on which the untrained network's iterates drift for some pairs."""
        generator = torch.Generator().manual_seed(1)
        src = torch.rand(3, 48, 3, generator=generator) - 0.5
        normals = F.normalize(torch.randn(3, 48, 3, generator=generator), dim=-1)
        torch.manual_seed(1)
        T = random_transform_paper(3, 2)
        return PairBatch(src, transform_points(T, src), normals, transform_normals(T, normals), gt_transform=T)

    def _fmr_pair(self) -> PairBatch:
        generator = torch.Generator().manual_seed(1)
        src = torch.rand(3, 48, 3, generator=generator) - 0.5
        torch.manual_seed(1)
        T = random_transform_paper(3, 10)
        return PairBatch(src, transform_points(T, src), gt_transform=T)

    @pytest.mark.parametrize(
        ("config", "keep_fraction"),
        [
            ({"name": "rpmnet", "feature_dim": 16, "num_neighbors": 8, "test_iters": 4}, 1.0),
            ({"name": "rpmnet", "feature_dim": 16, "num_neighbors": 8, "test_iters": 4}, 0.5),
            ({"name": "fmr", "dim_k": 32, "decoder_points": None, "test_iters": 5}, 1.0),
        ],
        ids=["rpmnet", "rpmnet-trimmed", "fmr"],
    )
    def test_best_fit_picks_an_earlier_iterate_and_leaves_the_list_alone(self, config, keep_fraction):
        from linereg.pointcloud import trimmed_chamfer_distance
        from linereg.registration.iterates import select_iterate

        batch = self._rpmnet_pair() if config["name"] == "rpmnet" else self._fmr_pair()
        torch.manual_seed(0)
        model = MODELS.build(config).eval()
        with torch.no_grad():
            output = model(batch)
        before = [T.clone() for T in output.transforms]
        src, tgt = batch.src_xyz, batch.tgt_xyz
        chosen, index = select_iterate(output.transforms, src, tgt, rule="best_fit", keep_fraction=keep_fraction)
        fits = [trimmed_chamfer_distance(transform_points(T, src), tgt, keep_fraction) for T in before]
        expected = torch.stack(fits).argmin(0)
        assert (expected < len(before) - 1).any()  # some pair is answered by an earlier iterate
        assert torch.equal(index, expected)
        for pair, iteration in enumerate(expected.tolist()):
            torch.testing.assert_close(chosen[pair], before[iteration][pair])
        assert len(output.transforms) == len(before)
        for original, returned in zip(before, output.transforms, strict=True):
            assert torch.equal(original, returned)

    @pytest.mark.parametrize("name", ["rpmnet", "fmr"])
    @pytest.mark.parametrize("switch", [{"keep_best_iterate": True}, {"fit_keep_fraction": 0.9}])
    def test_the_models_take_no_iterate_switch(self, name, switch):
        with pytest.raises(TypeError, match=next(iter(switch))):
            MODELS.build({"name": name, **switch})

    def test_training_returns_every_iterate(self):
        model = small_model("rpmnet").train()
        output = model(self._rpmnet_pair())
        assert len(output.transforms) == model.train_iters and "kept_iteration" not in output.extras
