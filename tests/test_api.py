"""``linereg.register``: inputs of every kind, the initial guess, trained networks, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import linereg
from linereg.datasets.procedural import procedural_shape
from linereg.io import write_point_cloud
from linereg.models import MODELS
from linereg.registration.robust_result import RobustResult
from linereg.registry import ArgumentError, UnknownNameError
from linereg.se3 import euler_to_rotmat, rt_to_matrix
from linereg.train.checkpoint import save_checkpoint

FAST = {"method": "icp_point"}


def pose(euler_deg, translation) -> np.ndarray:
    R = euler_to_rotmat(torch.deg2rad(torch.tensor(euler_deg, dtype=torch.float64)))
    return rt_to_matrix(R, torch.tensor(translation, dtype=torch.float64)).numpy()


def rotation_error_deg(A: np.ndarray, B: np.ndarray) -> float:
    cosine = (np.trace(A[:3, :3].T @ B[:3, :3]) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))


@pytest.fixture(scope="module")
def pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(src (600, 3), tgt (600, 3), T)`` with ``tgt = T src``, float64."""
    src = np.asarray(procedural_shape(np.random.default_rng(3)).sample(600, seed=3), dtype=np.float64)
    T = pose([40.0, -20.0, 25.0], [0.2, -0.1, 0.05])
    return src, src @ T[:3, :3].T + T[:3, 3], T


def test_the_default_solver_recovers_the_pose(pair):
    src, tgt, T = pair
    result = linereg.register(src, tgt, num_points=256)
    assert isinstance(result, linereg.RegistrationResult)
    assert result.transformation.shape == (4, 4) and result.transformation.dtype == np.float64
    assert rotation_error_deg(result.transformation, T) < 0.5
    assert result.fitness > 0.95 and 0 <= result.inlier_rmse < result.info["fitness_threshold"] and result.seconds > 0
    assert result.confident and result.info["method"]["name"] == "robust"
    assert isinstance(result.solution, RobustResult) and result.solution.rounds == 1  # the solver's typed record
    assert not {"rounds", "doubtful", "selection", "global_candidates"} & set(result.info)  # info: no field's values


def test_arrays_tensors_and_files_give_the_same_result(pair, tmp_path):
    src, tgt, _ = pair
    from_arrays = linereg.register(src.astype(np.float32), tgt.astype(np.float32), **FAST)
    from_tensors = linereg.register(torch.from_numpy(src).float(), torch.from_numpy(tgt).float(), **FAST)
    write_point_cloud(tmp_path / "src.ply", src.astype(np.float32))
    write_point_cloud(tmp_path / "tgt.ply", tgt.astype(np.float32))
    from_files = linereg.register(tmp_path / "src.ply", str(tmp_path / "tgt.ply"), **FAST)
    for other in (from_tensors, from_files):
        np.testing.assert_allclose(other.transformation, from_arrays.transformation, atol=1e-9)
        assert other.fitness == from_arrays.fitness


def test_open3d_clouds_are_accepted(pair):
    o3d = pytest.importorskip("open3d")
    src, tgt, T = pair
    clouds = [o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)) for points in (src, tgt)]
    result = linereg.register(*clouds, **FAST)
    assert rotation_error_deg(result.transformation, T) < 0.5


def test_init_is_honoured(pair):
    """A pose far beyond the search's reach is found from a nearby guess, and the guess is in the result."""
    src, _, _ = pair
    T = pose([170.0, 0.0, 20.0], [0.4, 0.1, 0.0])  # beyond ICP's reach without a guess
    tgt = src @ T[:3, :3].T + T[:3, 3]
    guess = pose([165.0, 3.0, 15.0], [0.35, 0.1, 0.05])
    result = linereg.register(src, tgt, init=guess, method="icp_point")
    assert rotation_error_deg(result.transformation, T) < 0.1
    np.testing.assert_allclose(result.info["init"], guess)
    without = linereg.register(src, tgt, method="icp_point")
    assert rotation_error_deg(without.transformation, T) > 10


def test_a_registered_method_with_options(pair):
    src, tgt, _ = pair
    result = linereg.register(src, tgt, method="icp_point", max_iterations=5, fitness_threshold=0.05)
    assert result.info["fitness_threshold"] == 0.05 and result.info["method"]["max_iterations"] == 5
    assert 0.0 <= result.fitness <= 1.0 and result.solution is None  # ICP keeps no typed record


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A checkpoint of ``python -m train``'s format holding a small untrained RPM-Net."""
    model_config = {"name": "rpmnet", "feature_dim": 16, "num_neighbors": 8, "test_iters": 2}
    torch.manual_seed(0)
    model = MODELS.build(model_config)
    run = tmp_path_factory.mktemp("run")
    state = {"config": {"model": model_config, "trainer": {"num_points": 256}}, "model": model.state_dict()}
    save_checkpoint(state, run / "checkpoints" / "best.pt")
    return run


def test_a_trained_network_registers_and_the_refinement_recovers_the_pose(pair, checkpoint):
    src, tgt, T = pair
    by_folder = linereg.register(src, tgt, method=checkpoint)
    by_file = linereg.register(src, tgt, method=str(checkpoint / "checkpoints" / "best.pt"))
    np.testing.assert_allclose(by_folder.transformation, by_file.transformation, atol=1e-6)
    np.testing.assert_allclose(by_folder.transformation, by_folder.info["network_transform"])
    rotation = by_folder.transformation[:3, :3]
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-5)
    refined = linereg.register(src, tgt, method=checkpoint, refine=True)
    assert rotation_error_deg(refined.transformation, T) < 0.5
    assert refined.info["checkpoint"].endswith("best.pt") and refined.confident


def _answering(transform: np.ndarray):
    """A solver stand-in that answers ``transform (4, 4)``."""
    from linereg.registration.methods import MethodResult

    return lambda *args, **kwargs: MethodResult(transform=np.array(transform, dtype=np.float64))


def _network_answering(transform: np.ndarray):
    """A ``predict_many`` stand-in whose network answers ``transform (4, 4)`` for every pair."""
    return lambda self, pairs, *args, **kwargs: [np.array(transform, dtype=np.float64) for _ in pairs]


def test_the_finish_polishes_a_right_network_pose_without_the_solver(pair, checkpoint, monkeypatch):
    """A network pose 3 degrees off is polished locally and trusted: the solver never runs."""
    from linereg.registration.learned import LearnedRegistration

    src, tgt, T = pair
    near = pose([3.0, 0.0, 0.0], [0.0, 0.0, 0.0]) @ T
    monkeypatch.setattr(LearnedRegistration, "predict_many", _network_answering(near))
    result = linereg.register(src, tgt, method=checkpoint, refine=True)
    assert result.info["path"] == "polished network" and not result.info["solver_ran"]
    assert rotation_error_deg(result.transformation, T) < 0.1 and result.confident


def test_a_wrong_network_pose_costs_time_not_accuracy(pair, checkpoint, monkeypatch):
    """A network pose 120 degrees off fails the check after its polish: the solver runs and its answer wins."""
    from linereg.registration.learned import LearnedRegistration

    src, tgt, T = pair
    far = pose([120.0, 30.0, 0.0], [0.3, 0.0, 0.0]) @ T
    monkeypatch.setattr(LearnedRegistration, "predict_many", _network_answering(far))
    result = linereg.register(src, tgt, method=checkpoint, refine=True)
    assert result.info["solver_ran"] and result.info["path"] == "solver"
    assert rotation_error_deg(result.transformation, T) < 0.5 and result.confident


def test_a_flip_of_the_solver_never_replaces_a_right_network_pose(pair, checkpoint, monkeypatch):
    """When the check doubts the polished network pose and the solver answers a flip, the network's pose stays."""
    from linereg.registration import learned
    from linereg.registration.robust import RobustRegistration

    src, tgt, T = pair
    monkeypatch.setattr(learned.LearnedRegistration, "predict_many", _network_answering(T))
    flipped = pose([180.0, 0.0, 0.0], [0.0, 0.0, 0.0]) @ T
    real_call = RobustRegistration.__call__

    def flipping(self, source, target, *rest):
        if self.options.coarse.steps == 0:  # the polish: doubted, so that the solver runs
            return real_call(self, source, target, *rest)
        return _answering(flipped)()

    monkeypatch.setattr(RobustRegistration, "__call__", flipping)
    monkeypatch.setattr(learned, "assess_registration", _doubting_the_first(learned.assess_registration))
    result = linereg.register(src, tgt, method=checkpoint, refine=True)
    assert result.info["solver_ran"] and result.info["path"] == "polished network"
    assert rotation_error_deg(result.transformation, T) < 0.1


def test_when_neither_answer_is_trusted_the_closer_one_is_kept(pair, checkpoint, monkeypatch):
    """A network pose 120 degrees off and the solver's right answer, both reported untrusted: the
    solver's answer fits the target better and is kept."""
    from linereg.registration import learned

    src, tgt, T = pair
    far = pose([120.0, 30.0, 0.0], [0.3, 0.0, 0.0]) @ T
    monkeypatch.setattr(learned.LearnedRegistration, "predict_many", _network_answering(far))
    monkeypatch.setattr(learned, "assess_registration", _doubting_all(learned.assess_registration))
    result = linereg.register(src, tgt, method=checkpoint, refine=True)
    assert result.info["solver_ran"] and result.info["path"] == "solver"
    assert rotation_error_deg(result.transformation, T) < 0.5


def test_fits_better_prefers_the_pose_nearer_the_target(pair):
    from linereg.registration.learned import fits_better

    src, tgt, T = pair
    near = pose([1.0, 0.0, 0.0], [0.0, 0.0, 0.0]) @ T
    far = pose([20.0, 0.0, 0.0], [0.0, 0.0, 0.0]) @ T
    assert fits_better(src, tgt, T, near) and fits_better(src, tgt, near, far)
    assert not fits_better(src, tgt, far, T)


def _doubting_all(assess):
    """``assess_registration`` that reports every answer not confident."""
    return lambda *args, **kwargs: assess(*args, **kwargs)._replace(confident=False)


def _doubting_the_first(assess):
    """``assess_registration`` that reports its first answer not confident (the others as they are)."""
    calls = []

    def judged(*args, **kwargs):
        found = assess(*args, **kwargs)
        calls.append(found)
        return found._replace(confident=False) if len(calls) == 1 else found

    return judged


@pytest.mark.parametrize(
    ("source", "error", "message"),
    [
        (np.zeros((10, 2)), ValueError, "source"),
        (np.full((10, 3), np.nan), ValueError, "source"),
        (np.zeros((2, 3)), ValueError, "source"),
        ([[0.0, 0.0, 0.0]] * 5, TypeError, "source: expected an"),
        ("no_such_file.ply", FileNotFoundError, "source=no_such_file.ply: no such file"),
    ],
    ids=["2d", "nan", "two-points", "list", "missing-file"],
)
def test_bad_clouds_are_named(pair, source, error, message):
    with pytest.raises(error, match=message):
        linereg.register(source, pair[1])


def test_bad_init_method_and_options_are_named(pair, tmp_path):
    src, tgt, _ = pair
    with pytest.raises(ValueError, match="init"):
        linereg.register(src, tgt, init=np.eye(3))
    with pytest.raises(ValueError, match="init"):
        linereg.register(src, tgt, init=2 * np.eye(4))
    with pytest.raises(UnknownNameError, match="icp_point"):
        linereg.register(src, tgt, method="nope")
    with pytest.raises(ArgumentError, match=r"'icp_point' got unknown argument\(s\) \['device'\]"):
        linereg.register(src, tgt, method="icp_point", device="cpu")
    with pytest.raises(ArgumentError, match="not_an_option"):
        linereg.register(src, tgt, not_an_option=1)
    with pytest.raises(ValueError, match="is a folder"):
        linereg.register(tmp_path, tgt)


def test_the_default_method_runs_on_the_cpu_and_refuses_other_devices(pair):
    from linereg.registration.api import _build
    from linereg.registration.robust import RobustRegistration

    assert isinstance(_build("robust", None, {})[0], RobustRegistration)
    assert isinstance(_build("robust", "cpu", {})[0], RobustRegistration)
    with pytest.raises(KeyError, match="method='default': not a registered method"):
        _build("default", None, {})
    with pytest.raises(ValueError, match="method=robust runs on the CPU; device=cuda is not supported"):
        linereg.register(*pair[:2], device="cuda")


def test_every_method_is_scored_by_one_quality_function(pair):
    """Fitness and inlier RMSE come from evaluate_registration for every method, the init included."""
    from linereg.registration.evaluation import ASSESS_SOURCE_POINTS, ASSESS_TARGET_POINTS, evaluate_registration

    src, tgt, _ = pair
    guess = pose([35.0, -15.0, 20.0], [0.15, -0.1, 0.0])
    for result in (linereg.register(src, tgt, **FAST), linereg.register(src, tgt, init=guess, **FAST)):
        assert len(src) <= ASSESS_SOURCE_POINTS and len(tgt) <= ASSESS_TARGET_POINTS
        expected = evaluate_registration(src, tgt, result.info["fitness_threshold"], result.transformation)
        assert result.fitness == pytest.approx(expected.fitness) and expected.correspondences > 0
        assert result.inlier_rmse == pytest.approx(expected.inlier_rmse)


def test_evaluate_registration_counts_inliers_as_open3d_does():
    from linereg.registration.evaluation import evaluate_registration

    src = np.array([[0.0, 0, 0], [1, 0, 0], [5, 0, 0]])
    tgt = np.array([[0.0, 0.1, 0], [1, 0, 0.2]])
    quality = evaluate_registration(src, tgt, 0.15)
    assert quality.fitness == pytest.approx(1 / 3) and quality.correspondences == 1
    assert quality.inlier_rmse == pytest.approx(0.1)
    assert tuple(evaluate_registration(src, tgt, 0.01, np.eye(4))) == (0.0, 0.0, 0)


def test_evaluate_registration_matches_open3d(pair):
    o3d = pytest.importorskip("open3d")
    from linereg.registration.evaluation import evaluate_registration

    src, tgt, T = pair
    noisy = T.copy()
    noisy[:3, 3] += 0.01
    clouds = [o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)) for points in (src, tgt)]
    for transform, distance in ((noisy, 0.02), (np.eye(4), 0.3)):
        theirs = o3d.pipelines.registration.evaluate_registration(*clouds, distance, transform)
        ours = evaluate_registration(src, tgt, distance, transform)
        assert ours.fitness == pytest.approx(theirs.fitness) and ours.inlier_rmse == pytest.approx(theirs.inlier_rmse)
        assert ours.correspondences == len(theirs.correspondence_set)


def test_register_many_answers_in_order_as_register_does(pair, checkpoint):
    """The network's forward in batches gives each pair the pose a single call gives it; results keep the order."""
    src, tgt, _ = pair
    other = pose([0.0, 10.0, 0.0], [0.0, 0.1, 0.0])
    pairs = [(src, tgt), (src, src @ other[:3, :3].T + other[:3, 3]), (src, tgt)]
    many = list(linereg.register_many(pairs, method=checkpoint, batch_size=2, progress=False))
    assert len(many) == 3
    for result, (source, target) in zip(many, pairs, strict=True):
        single = linereg.register(source, target, method=checkpoint)
        np.testing.assert_allclose(result.transformation, single.transformation, atol=1e-5)
        assert result.confident == single.confident and result.info["path"] == "network"
    solved = list(linereg.register_many(iter(pairs[:2]), method="icp_point", progress=False))
    assert rotation_error_deg(solved[1].transformation, other) < 0.5


def test_register_many_drops_a_network_that_costs_more_than_it_saves(pair, checkpoint, monkeypatch):
    """A network 120 degrees off on every pair: each falls back to the solver, so its path costs more
    than the solver's; after the probe the remaining pairs go straight to the solver, as right."""
    from linereg.registration import learned, many

    src, tgt, T = pair
    far = pose([120.0, 30.0, 0.0], [0.3, 0.0, 0.0]) @ T
    forwards = []

    def counting(self, pairs, *args, **kwargs):
        forwards.append(len(pairs))
        return _network_answering(far)(self, pairs)

    monkeypatch.setattr(learned.LearnedRegistration, "predict_many", counting)
    monkeypatch.setattr(many, "PROBE_PAIRS", 2)
    run = list(linereg.register_many([(src, tgt)] * 4, method=checkpoint, refine=True, batch_size=2, progress=False))
    assert forwards == [2]
    assert [result.info.get("network_skipped", False) for result in run] == [False, False, True, True]
    assert all(result.info["path"] == "solver" and result.info["solver_ran"] for result in run)
    assert all(rotation_error_deg(result.transformation, T) < 0.5 and result.confident for result in run)
    kept = linereg.register_many(
        [(src, tgt)] * 4, method=checkpoint, refine=True, batch_size=2, progress=False, keep_network=True
    )
    assert not any(result.info.get("network_skipped") for result in kept) and forwards == [2, 2, 2]


def test_the_network_ledger_compares_the_networks_path_with_the_solvers():
    from linereg.registration.many import PROBE_PAIRS, NetworkLedger

    def finished(polish: float, solver: float) -> dict:
        return {"polish_seconds": polish, "solver_seconds": solver, "solver_ran": solver > 0}

    trusted = NetworkLedger()
    for _ in range(PROBE_PAIRS + 2):
        trusted.record(0.5, finished(0.5, 0.0))
    assert not trusted.slower()  # no pair fell back: the solver's time is unknown, the network stays
    mixed, costly = NetworkLedger(), NetworkLedger()
    for index in range(PROBE_PAIRS):
        mixed.record(0.05, finished(0.05, 1.0 if index % 4 == 0 else 0.0))  # 0.35 s a pair against 1 s
        costly.record(0.1, finished(0.05, 0.2 if index % 2 else 0.0))  # 0.25 s a pair against 0.2 s
        assert not costly.slower() or index == PROBE_PAIRS - 1
    assert not mixed.slower() and costly.slower()


def test_register_many_names_the_bad_pair(pair):
    src, tgt, _ = pair
    with pytest.raises(ValueError, match=r"pairs\[1\] target"):
        list(linereg.register_many([(src, tgt), (src, np.full((5, 3), np.nan))], method="icp_point", progress=False))
    with pytest.raises(TypeError, match=r"pairs\[0\]"):
        list(linereg.register_many([src], progress=False))


def test_the_finish_polishes_from_the_networks_pose_translation_included(pair):
    """A view of part of the target: the polish starts where the network put the view, not at the
    target's centroid (where centring both clouds would move it)."""
    from linereg.registration.learned import Finish

    src, tgt, T = pair
    view = src[src[:, 0] > np.quantile(src[:, 0], 0.6)]

    polished = Finish().polish(view, tgt, T)

    assert rotation_error_deg(polished.transform, T) < 0.1
    assert np.linalg.norm(polished.transform[:3, 3] - T[:3, 3]) < 1e-2
