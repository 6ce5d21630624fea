"""The optimisation-based registration solvers and ``python -m train.register``."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from linereg.io import read_point_cloud, read_transform, write_point_cloud, write_transform
from linereg.metrics import registration_errors
from linereg.paths import REPO_ROOT
from linereg.registration import METHODS
from linereg.registration.solvers import start_poses
from linereg.se3 import euler_to_rotmat, rotation_angle, rt_to_matrix
from linereg.train.register import RegisterError, method_config, parse_init, register_files
from tests.conftest import compose_register


def surface(n: int, seed: int) -> np.ndarray:
    """Samples of an asymmetric bumpy ellipsoid (float32, unit scale)."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    bump = 1.0 + 0.25 * np.sin(3.0 * x[:, 0]) * np.cos(2.0 * x[:, 1])
    return (x * bump[:, None] * np.array([1.4, 1.0, 0.7])).astype(np.float32)


def pose(angles_deg, t) -> np.ndarray:
    R = euler_to_rotmat(torch.tensor(angles_deg, dtype=torch.float64) * math.pi / 180)
    return rt_to_matrix(R, torch.tensor(t, dtype=torch.float64)).numpy()


def apply(T: np.ndarray, x: np.ndarray) -> np.ndarray:
    return (x @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


def err_r(T_pred: np.ndarray, T_gt: np.ndarray, src: np.ndarray) -> float:
    errors = registration_errors(
        torch.from_numpy(T_pred)[None], torch.from_numpy(T_gt)[None], torch.from_numpy(src).double()[None]
    )
    return float(errors["err_r_deg"][0])


FAST_ADAM = {
    "name": "adam_loss",
    "stages": [
        {"loss": {"name": "chamfer_welsch", "nu0": 2.0}, "iterations": 40, "lr": 0.03, "points": 256},
        {"loss": {"name": "line_intersection", "variant": "linereg", "num_lines": 3000}, "iterations": 60, "lr": 0.01},
    ],
    "num_points": 512,
}


@pytest.mark.parametrize(
    "config", [FAST_ADAM, {"name": "svd_irls", "iterations": 25, "num_lines": 4000, "num_points": 512}]
)
def test_solvers_recover_a_known_pose(config):
    src = surface(800, 0)
    T = pose([20, -15, 10], [0.3, -0.2, 0.1])
    tgt = apply(T, surface(800, 0))
    result = METHODS.build(config)(src, tgt)
    assert err_r(result.transform, T, src) < 1.0
    assert result.seconds > 0 and len(result.info["loss_curve"]) > 0


def test_multi_start_escapes_the_local_minimum_of_a_single_start():
    src = surface(800, 0)
    T = pose([100, 40, 0], [0.2, 0.0, 0.0])
    tgt = apply(T, surface(800, 0))
    single = METHODS.build({**FAST_ADAM, "starts": 1})(src, tgt)
    multi = METHODS.build({**FAST_ADAM, "starts": 7})(src, tgt)
    assert err_r(single.transform, T, src) > 90.0
    assert err_r(multi.transform, T, src) < 1.0 and multi.info["start"] != 0


def test_registration_is_deterministic_given_the_seed():
    src = surface(500, 4)
    tgt = apply(pose([30, 20, -10], [0.1, 0.0, 0.2]), surface(500, 4))
    first, second = (METHODS.build({**FAST_ADAM, "seed": 3})(src, tgt) for _ in range(2))
    np.testing.assert_array_equal(first.transform, second.transform)
    assert first.info["start"] == second.info["start"]


def test_start_poses():
    poses = start_poses(7, 90.0)
    assert poses.shape == (7, 4, 4)
    np.testing.assert_allclose(poses[0].numpy(), np.eye(4))
    np.testing.assert_allclose(rotation_angle(poses[1:, :3, :3]).numpy(), np.full(6, math.pi / 2))
    np.testing.assert_allclose(poses[1:, :3, 3].numpy(), 0.0)
    np.testing.assert_allclose(poses[1, :3, :3].numpy() @ [0, 1, 0], [0, 0, 1], atol=1e-12)
    with pytest.raises(ValueError, match=r"starts must be in 1\.\.7"):
        start_poses(8)


def test_identical_clouds_give_the_identity():
    cloud = surface(600, 1)
    result = METHODS.build({**FAST_ADAM, "num_points": 400})(cloud, cloud)
    np.testing.assert_allclose(result.transform, np.eye(4), atol=2e-3)


def test_supervised_loss_is_rejected():
    with pytest.raises(ValueError, match="ground truth"):
        METHODS.build({"name": "adam_loss", "stages": [{"loss": {"name": "gt_dcp"}, "iterations": 1, "lr": 0.1}]})


def test_a_loss_that_is_no_alignment_metric_is_rejected():
    with pytest.raises(ValueError, match="not an alignment metric"):
        stage = {"loss": {"name": "rpmnet_outlier"}, "iterations": 1, "lr": 0.1}
        METHODS.build({"name": "adam_loss", "stages": [stage]})


def test_unknown_stage_preset_and_keys():
    with pytest.raises(ValueError, match="preset"):
        METHODS.build({"name": "adam_loss", "stages": "fastest"})
    with pytest.raises(TypeError, match="stage key"):
        METHODS.build(
            {"name": "adam_loss", "stages": [{"loss": {"name": "chamfer"}, "iterations": 1, "lr": 0.1, "mom": 1}]}
        )


def _compose(**overrides):
    return compose_register(**{"progress": "false", "picture": "false", **overrides})


def test_register_command_writes_its_outputs(tmp_path):
    src = surface(700, 2)
    T = pose([15, 10, -5], [0.1, 0.2, -0.1])
    write_point_cloud(tmp_path / "a.ply", src)
    np.save(tmp_path / "b.npy", apply(T, surface(900, 2)[:900]))
    write_transform(tmp_path / "gt.txt", T)
    cfg = _compose(source=tmp_path / "a.ply", target=tmp_path / "b.npy", gt=tmp_path / "gt.txt", num_points=512)
    _, report = register_files(cfg, tmp_path / "run")
    out = tmp_path / "run"
    estimate = read_transform(out / "transform.txt")
    assert err_r(estimate, T, src) < 1.0
    registered = read_point_cloud(out / "registered.ply")
    np.testing.assert_allclose(registered.xyz, apply(estimate, src), atol=1e-5)
    saved = json.loads((out / "result.json").read_text())
    assert saved["metrics"]["err_r_deg"] < 1.0 and saved["seconds"] > 0
    assert saved["fitness"] > 0.9 and 0 < saved["inlier_rmse"] < 0.1 and saved["confident"] is True
    assert saved["solver"]["rounds"] == 1 and saved["solver"]["selection"] == "fixed" and "rounds" not in saved["info"]
    assert report["source_points"] == 700 and report["target_points"] == 900
    assert not (out / "registration.png").exists()


def test_a_registered_baseline_gets_its_flag_from_the_same_test(tmp_path):
    """``method=icp_point`` runs as any method does (no ``refine`` reaches it) and is flagged by the same test."""
    src = surface(600, 4)
    write_point_cloud(tmp_path / "a.xyz", src)
    write_point_cloud(tmp_path / "b.xyz", apply(pose([4, -3, 2], [0.03, 0.0, -0.02]), surface(800, 5)))
    _, report = register_files(
        _compose(source=tmp_path / "a.xyz", target=tmp_path / "b.xyz", method="icp_point"), tmp_path / "run"
    )
    assert report["method"]["name"] == "icp_point" and isinstance(report["confident"], bool)


def test_register_with_a_chosen_loss_and_the_svd_solver(tmp_path):
    """``method=adam_loss`` and ``method=svd_irls`` take their settings from the config."""
    src = surface(500, 3)
    write_point_cloud(tmp_path / "a.xyz", src)
    write_point_cloud(tmp_path / "b.xyz", apply(pose([5, 0, 0], [0.05, 0, 0]), src))
    for overrides in (
        {"method": "adam_loss", "loss": "chamfer", "iterations": 60},
        {"method": "svd_irls", "svd.iterations": 10},
    ):
        cfg = _compose(source=tmp_path / "a.xyz", target=tmp_path / "b.xyz", num_points=400, **overrides)
        _, report = register_files(cfg, tmp_path / "run")
        assert np.isfinite(np.array(report["transform"])).all() and report["method"]["name"] == overrides["method"]


def test_each_method_builds_its_config_from_the_command_settings(monkeypatch):
    """``method_config`` asks the method's own type (``from_register_settings``), with no list of
    method names: a newly registered method is read the same way; one without the hook goes as a name."""
    from linereg.registration import METHODS

    class Echo:
        @classmethod
        def from_register_settings(cls, settings):
            return {"name": "echo", "points": settings["num_points"], "lines": settings["svd"]["options"]["num_lines"]}

    monkeypatch.setitem(METHODS._builders, "echo", Echo)
    assert method_config(_compose(method="echo", num_points=77)) == {"name": "echo", "points": 77, "lines": 8000}
    assert method_config(_compose(method="icp_point")) == "icp_point"
    adam = method_config(_compose(method="adam_loss", loss="chamfer", iterations=9, lr=0.5, starts=1))
    assert adam["stages"] == [{"loss": {"name": "chamfer"}, "iterations": 9, "lr": 0.5}] and adam["starts"] == 1
    svd = method_config(_compose(method="svd_irls", **{"svd.iterations": 7, "seed": 3}))
    assert (svd["iterations"], svd["num_lines"], svd["variant"], svd["seed"]) == (7, 8000, "linereg", 3)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda p: None, "no such file"),
        (lambda p: write_point_cloud(p, np.zeros((1, 3), np.float32)), "at least 3"),
        (lambda p: np.save(p.with_suffix(".npy"), np.full((10, 3), np.nan)), "NaN"),
    ],
    ids=["missing", "one-point", "nan"],
)
def test_bad_sources_give_clear_errors(tmp_path, make, message):
    target = tmp_path / "b.ply"
    write_point_cloud(target, surface(100, 4))
    source = tmp_path / "a.ply"
    make(source)
    if not source.exists() and source.with_suffix(".npy").exists():
        source = source.with_suffix(".npy")
    cfg = _compose(source=source, target=target)
    with pytest.raises((FileNotFoundError, ValueError), match=message):
        register_files(cfg, tmp_path / "run")


def test_non_rigid_ground_truth_is_rejected(tmp_path):
    write_point_cloud(tmp_path / "a.ply", surface(100, 5))
    (tmp_path / "gt.txt").write_text("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    cfg = _compose(source=tmp_path / "a.ply", target=tmp_path / "a.ply", gt=tmp_path / "gt.txt")
    with pytest.raises(ValueError, match="rigid"):
        register_files(cfg, tmp_path / "run")


def test_unknown_config_key_is_an_error():
    with pytest.raises(Exception, match="nonsense"):
        _compose(source="a", target="b", nonsense=1)


def test_init_guess_is_applied_before_the_search(tmp_path):
    src = surface(600, 6)
    T = pose([170, 0, 20], [0.4, 0.1, 0.0])  # beyond the multi-start's reach without a guess
    write_point_cloud(tmp_path / "a.ply", src)
    write_point_cloud(tmp_path / "b.ply", apply(T, src))
    guess = pose([165, 3, 15], [0.35, 0.1, 0.05])
    write_transform(tmp_path / "init.txt", guess)
    for init in (tmp_path / "init.txt", ",".join(f"{v:.17g}" for v in guess.ravel())):
        cfg = _compose(source=tmp_path / "a.ply", target=tmp_path / "b.ply", init=f"'{init}'", num_points=400)
        _, report = register_files(cfg, tmp_path / "run")
        assert err_r(np.array(report["transform"]), T, src) < 0.5
        np.testing.assert_allclose(report["init"], guess)


def test_parse_init_accepts_files_lists_and_identity(tmp_path):
    np.testing.assert_array_equal(parse_init("identity"), np.eye(4))
    assert parse_init(None) is None
    np.testing.assert_array_equal(parse_init([1, 0, 0, 2, 0, 1, 0, 3, 0, 0, 1, 4]), pose([0, 0, 0], [2, 3, 4]))
    with pytest.raises(RegisterError, match=r"init=.*expected 16 \(4x4\) or 12"):
        parse_init("1 2 3")
    with pytest.raises(RegisterError, match=r"init=.*rigid"):
        parse_init(" ".join(["2"] + ["0"] * 4 + ["1"] + ["0"] * 4 + ["1"] + ["0"] * 4 + ["1"]))
    with pytest.raises(RegisterError, match=r"init=.*not a file"):
        parse_init("odometry.txt")
    with pytest.raises(RegisterError, match=r"init=.*is a folder"):
        parse_init(str(tmp_path))


def test_a_folder_given_as_source_is_named(tmp_path):
    write_point_cloud(tmp_path / "b.ply", surface(100, 4))
    cfg = _compose(source=tmp_path, target=tmp_path / "b.ply")
    with pytest.raises(RegisterError, match=f"source={tmp_path}: is a folder"):
        register_files(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_coincident_points_are_an_error_and_collinear_points_a_warning(tmp_path):
    write_point_cloud(tmp_path / "b.ply", surface(300, 4))
    np.savetxt(tmp_path / "same.xyz", np.ones((100, 3)))
    cfg = _compose(source=tmp_path / "same.xyz", target=tmp_path / "b.ply")
    with pytest.raises(RegisterError, match="source: all 100 points coincide"):
        register_files(cfg, tmp_path / "run")
    np.savetxt(tmp_path / "line.xyz", np.outer(np.arange(6.0), [1.0, 2.0, 3.0]))
    cfg = _compose(source=tmp_path / "line.xyz", target=tmp_path / "b.ply")
    _, report = register_files(cfg, tmp_path / "run")
    assert any("collinear" in note for note in report["warnings"])


def test_loss_without_the_adam_solver_is_an_error(tmp_path):
    write_point_cloud(tmp_path / "a.ply", surface(100, 4))
    cfg = _compose(source=tmp_path / "a.ply", target=tmp_path / "a.ply", loss="chamfer")
    with pytest.raises(RegisterError, match="loss=chamfer needs method=adam_loss"):
        register_files(cfg, tmp_path / "run")


def test_the_command_fails_cleanly_and_leaves_no_folder(tmp_path):
    write_point_cloud(tmp_path / "b.ply", surface(100, 4))
    command = [sys.executable, "-m", "train.register", f"source={tmp_path}", f"target={tmp_path / 'b.ply'}"]
    done = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, env=_repo_env(), timeout=300)
    assert done.returncode == 2
    assert f"source={tmp_path}: is a folder" in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "outputs").exists()


def _repo_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT), env.get("PYTHONPATH", "")])
    return env


def test_the_robust_solver_runs_in_numpy_on_the_cpu_and_refuses_other_devices(tmp_path):
    config = method_config(_compose(source="a", target="b"))
    assert isinstance(config.pop("progress"), bool)
    assert config == {"name": "robust", "options": {}, "num_points": 2048}
    write_point_cloud(tmp_path / "a.ply", surface(100, 4))
    on_gpu = _compose(source=tmp_path / "a.ply", target=tmp_path / "a.ply", device="cuda")
    with pytest.raises(RegisterError, match="method=robust runs on the CPU; device=cuda is not supported"):
        register_files(on_gpu, tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_keep_network_reaches_register_many(tmp_path, monkeypatch):
    """``pairs=<folder> keep_network=true``: the folder's pairs reach ``register_many`` with it."""
    from linereg.registration import many
    from linereg.train.register import _register_pairs

    folder = tmp_path / "pairs"
    folder.mkdir()
    write_point_cloud(folder / "a_src.ply", surface(200, 0))
    write_point_cloud(folder / "a_tgt.ply", surface(200, 0))
    seen, register_many = {}, many.register_many

    def recording(pairs, **kwargs):
        seen.update(kwargs)
        return register_many(pairs, **kwargs)

    monkeypatch.setattr(many, "register_many", recording)
    for keep in (False, True):
        _register_pairs(_compose(pairs=folder, method="icp_point", keep_network=keep), tmp_path / f"run{keep}")
        assert seen["keep_network"] is keep


def test_a_folder_of_pairs_goes_into_one_table_and_resumes(tmp_path, capsys):
    """``pairs=<folder>``: one row per pair in name order, errors where ground truth exists; a rerun
    in the same run folder registers only the pairs the table lacks."""
    import csv

    from linereg.train.register import _register_pairs

    folder = tmp_path / "pairs"
    folder.mkdir()
    truths = {}
    for index, name in enumerate(("b", "a", "c")):
        T = pose([10.0 * (index + 1), 5.0, 0.0], [0.05, 0.0, 0.02])
        write_point_cloud(folder / f"{name}_src.ply", surface(600, index))
        write_point_cloud(folder / f"{name}_tgt.ply", apply(T, surface(600, index)))
        write_transform(folder / f"{name}_gt.txt", T)
        truths[name] = T
    out = tmp_path / "run"
    (folder / "c_src.ply").rename(tmp_path / "held_back.ply")
    (folder / "c_tgt.ply").rename(tmp_path / "held_back_tgt.ply")
    (folder / "c_gt.txt").rename(tmp_path / "held_back_gt.txt")
    _register_pairs(_compose(pairs=folder, method="icp_point"), out)
    for kind, target in (("src", "c_src.ply"), ("tgt", "c_tgt.ply"), ("gt", "c_gt.txt")):
        source = {"src": "held_back.ply", "tgt": "held_back_tgt.ply", "gt": "held_back_gt.txt"}[kind]
        (tmp_path / source).rename(folder / target)
    _register_pairs(_compose(pairs=folder, method="icp_point"), out)
    assert "1 pairs registered (2 already in the table)" in capsys.readouterr().out
    with open(out / "results.csv", newline="") as stream:
        rows = list(csv.DictReader(stream))
    assert [row["name"] for row in rows] == ["a", "b", "c"]
    for row in rows:
        transform = np.array([float(value) for value in row["transform"].split()]).reshape(4, 4)
        assert float(row["err_r_deg"]) == pytest.approx(err_r(transform, truths[row["name"]], surface(10, 0)), abs=1e-4)
        assert row["path"] == "method" and row["confident"] in ("true", "false")


def test_pairs_refuses_one_pair_arguments(tmp_path):
    from linereg.train.register import _register_pairs

    with pytest.raises(RegisterError, match="source= is for one pair"):
        _register_pairs(_compose(pairs=tmp_path, source=tmp_path / "a.ply"), tmp_path / "run")
    with pytest.raises(RegisterError, match=f"pairs={tmp_path}"):
        _register_pairs(_compose(pairs=tmp_path), tmp_path / "run")
