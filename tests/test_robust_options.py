"""The settings of the ``register`` default (:mod:`linereg.registration.robust_options`): checks,
the flat names derived from the dataclasses, and the command-line form of its docstring."""

from __future__ import annotations

import dataclasses
import json
import re
import sys
from typing import ClassVar

import numpy as np
import pytest

from linereg.io import write_point_cloud
from linereg.registration import METHODS, robust_options
from linereg.registration.robust_options import FLAT_KEYS, RobustOptions

ACCEPTED = (
    "starts coarse_points coarse_sides coarse_nu0 coarse_steps explore_steps explore_lr merge_distance "
    "polish_steps polish_nu polish_end polish_settle fine_end fine_fitness "
    "plane_steps plane_nu plane_neighbours plane_epsilon coincident_distance coincident_share "
    "select_nu doubtful_select doubt_ratio distinct_deg max_cost min_fitness fitness_spacings rounds "
    "search_rotations search_radius search_spacing search_points search_nu search_cell search_keep "
    "global_candidates feature_points dense_points dense_keep dense_start dense_steps dense_end dense_settle "
    "dense_plane"
).split()
"""The flat names users type: a new field may add one, none may change."""


def options(**flat) -> RobustOptions:
    return RobustOptions.from_mapping(flat)


def test_options_are_checked():
    with pytest.raises(ValueError, match="coarse_points must be > 0"):
        options(coarse_points=0)
    with pytest.raises(ValueError, match="rounds must be 1, 2 or 3"):
        options(rounds=4)
    with pytest.raises(ValueError, match="min_fitness must be in"):
        options(min_fitness=1.5)
    with pytest.raises(ValueError, match="plane_steps must be >= 0"):
        options(plane_steps=-1)
    with pytest.raises(ValueError, match="plane_neighbours must be >= 3"):
        options(plane_neighbours=2)
    with pytest.raises(ValueError, match="plane_epsilon must be > 0"):
        options(plane_epsilon=0.0)
    with pytest.raises(ValueError, match="coincident_share must be in"):
        options(coincident_share=2.0)
    with pytest.raises(ValueError, match="doubtful_select must be 'polish' or 'fixed'"):
        options(doubtful_select="line")
    with pytest.raises(ValueError, match="global_candidates must be 'doubtful', 'always' or 'never'"):
        options(global_candidates="sometimes")
    assert options(global_candidates="always").global_stage.candidates == "always"
    with pytest.raises(ValueError, match="coarse_sides must be"):
        options(coarse_sides=("both", "target"))
    with pytest.raises(ValueError, match="search_keep must be > 0"):
        options(search_keep=0)
    assert options(coarse_sides=["source"]).coarse.sides == ("source",)
    with pytest.raises(TypeError, match="unknown option"):
        METHODS.build({"name": "robust", "options": {"startz": 3}})
    with pytest.raises(TypeError, match="unknown polish option"):
        options(polish={"stepz": 3})
    with pytest.raises(ValueError, match="method=robust runs on the CPU; device=cuda is not supported"):
        METHODS.build({"name": "robust", "device": "cuda"})


def test_every_flat_key_sets_its_group_field_and_groups_work_too():
    """One mapping from the flat keys users pass to the stage groups: each key lands in its field."""
    defaults = RobustOptions()
    groups = [field.name for field in dataclasses.fields(defaults)]
    special = {
        "coarse_sides": ("source",),
        "doubtful_select": "fixed",
        "rounds": 2,
        "doubt_ratio": 1.5,
        "global_candidates": "never",
    }
    for key, (group, name) in FLAT_KEYS.items():
        default = getattr(getattr(defaults, group), name)
        value = special[key] if key in special else default + 1 if isinstance(default, int) else 0.9 * default
        changed = RobustOptions.from_mapping({key: value})
        assert getattr(getattr(changed, group), name) == value, key
        assert all(getattr(changed, other) == getattr(defaults, other) for other in groups if other != group)
    assert len(FLAT_KEYS) == sum(len(dataclasses.fields(getattr(defaults, group))) for group in groups)
    nested = RobustOptions.from_mapping({"polish": {"steps": 30}, "starts": 7})
    assert nested.polish.steps == 30 and nested.coarse.starts == 7


def test_the_flat_names_are_the_accepted_ones():
    assert list(FLAT_KEYS) == ACCEPTED


def test_two_fields_with_one_flat_name_fail(monkeypatch):
    @dataclasses.dataclass(frozen=True)
    class Clashing:
        prefix: ClassVar[str] = "coarse"
        points: int = 1

    monkeypatch.setitem(robust_options._GROUPS, "clashing", Clashing)
    with pytest.raises(TypeError, match=r"clashing\.points: the flat name 'coarse_points' is taken"):
        robust_options._flat_keys()


def test_the_docstrings_command_line_runs(tmp_path, monkeypatch):
    """The module docstring's ``linereg-register`` example, as written, on two small clouds."""
    from linereg.train import register

    (example,) = re.findall(r"``(linereg-register [^`]+)``", robust_options.__doc__)
    command, *arguments = example.split()
    rng = np.random.default_rng(0)
    cloud = rng.normal(size=(300, 3)) * [1.4, 1.0, 0.6]
    write_point_cloud(tmp_path / "a.ply", cloud)
    write_point_cloud(tmp_path / "b.ply", cloud + 0.1)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", [command, *arguments, "progress=false", f"hydra.run.dir={tmp_path}/run"])
    register.main()
    report = json.loads((tmp_path / "run" / "result.json").read_text())
    assert report["method"]["options"] == {"starts": 7} and report["confident"]
