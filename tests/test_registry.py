"""Tests for linereg.registry."""

from __future__ import annotations

import pytest

from linereg.registry import Registry


@pytest.fixture
def registry() -> Registry:
    losses = Registry("loss")

    @losses.register("chamfer", needs_gt=False)
    def _chamfer(scale: float = 1.0):
        return ("chamfer", scale)

    @losses.register("line_intersection", needs_gt=False, paper=True)
    def _line(**kwargs):
        return ("line", kwargs)

    @losses.register("supervised_mse", needs_gt=True)
    def _mse():
        return "mse"

    return losses


def test_build_passes_keyword_arguments(registry):
    assert registry.build("chamfer") == ("chamfer", 1.0)
    assert registry.build("chamfer", scale=2.0) == ("chamfer", 2.0)
    assert registry.build("line_intersection", num_lines=15000) == ("line", {"num_lines": 15000})


def test_decorator_returns_the_builder(registry):
    def builder():
        return 1

    assert registry.register("one")(builder) is builder


def test_unknown_name_lists_valid_names(registry):
    with pytest.raises(
        KeyError,
        match="unknown loss 'chamfr'; registered: chamfer, line_intersection, supervised_mse",
    ):
        registry.build("chamfr")


def test_unknown_name_in_empty_registry():
    with pytest.raises(KeyError, match=r"unknown model 'dcp'; registered: \(none\)"):
        Registry("model").get("dcp")


def test_names_sorted_and_wildcard(registry):
    assert registry.names() == ["chamfer", "line_intersection", "supervised_mse"]
    assert registry.names("*_*") == ["line_intersection", "supervised_mse"]
    assert registry.names("ch*") == ["chamfer"]
    assert registry.names("nothing*") == []


def test_contains(registry):
    assert "chamfer" in registry
    assert "dcp" not in registry


def test_metadata(registry):
    assert registry.metadata("line_intersection") == {"needs_gt": False, "paper": True}
    assert registry.metadata("supervised_mse")["needs_gt"] is True
    registry.metadata("chamfer")["needs_gt"] = True
    assert registry.metadata("chamfer") == {"needs_gt": False}, "metadata must be returned as a copy"
    with pytest.raises(KeyError, match="unknown loss 'nope'"):
        registry.metadata("nope")


def test_duplicate_registration_warns_and_replaces(registry):
    with pytest.warns(UserWarning, match="loss 'chamfer' registered twice; the later one wins"):

        @registry.register("chamfer", needs_gt=True)
        def _other():
            return "other"

    assert registry.build("chamfer") == "other"
    assert registry.metadata("chamfer") == {"needs_gt": True}
