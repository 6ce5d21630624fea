"""Checkpoints: atomic writes, safe loading, RNG states, and exact resumption of a run."""

from __future__ import annotations

import json
import os
import random
import re
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from linereg.losses import build_loss
from linereg.train import checkpoint, loop, randomness, resume
from linereg.train.evaluate import evaluate
from linereg.train.logging import RunLogger, read_scalars
from tests.conftest import compose_config

ROOT = Path(__file__).resolve().parent.parent
SMALL = ["model.num_neighbors=8", "loss.num_lines=300"]


def tiny_config(output_dir: Path, *overrides: str):
    """``debug=tiny`` with the run folder in ``output_dir``."""
    return compose_config(
        "train", ["debug=tiny", f"paths.root_dir={ROOT}", f"paths.output_dir={output_dir}", *SMALL, *overrides]
    )


def _step_losses(run_dir: Path) -> dict[int, float]:
    """``{global step: training loss}``, the last record winning (a resumed run re-logs)."""
    return {record["step"]: record["train/loss"] for record in read_scalars(run_dir) if "train/loss" in record}


def _interrupt_at(monkeypatch, epoch: int) -> None:
    """Make the run raise KeyboardInterrupt when epoch ``epoch`` (0-based) starts."""
    original = loop.Trainer._train_epoch

    def train_epoch(self):
        if self.epoch == epoch:
            raise KeyboardInterrupt
        return original(self)

    monkeypatch.setattr(loop.Trainer, "_train_epoch", train_epoch)


@pytest.mark.parametrize(
    ("overrides", "interrupt_epoch"),
    [
        ([], 2),  # resumes into the next curriculum stage
        (["curriculum=none", "curriculum.stages.full.epochs=3", "scheduler=cosine"], 1),  # inside a stage
    ],
    ids=["stage_boundary", "mid_stage"],
)
def test_resume_gives_the_same_next_step(tmp_path, monkeypatch, overrides, interrupt_epoch):
    uninterrupted = loop.train(tiny_config(tmp_path / "a", *overrides))

    _interrupt_at(monkeypatch, interrupt_epoch)
    with pytest.raises(KeyboardInterrupt):
        loop.train(tiny_config(tmp_path / "b", *overrides))
    saved = checkpoint.load_checkpoint(tmp_path / "b" / "checkpoints" / "last.pt")
    assert saved["progress"]["epoch"] == interrupt_epoch  # nothing but the current epoch is lost
    monkeypatch.undo()
    resumed = loop.train(tiny_config(tmp_path / "b", *overrides, "resume=true"))

    first_resumed_step = saved["progress"]["global_step"] + 1
    losses_a, losses_b = _step_losses(tmp_path / "a"), _step_losses(tmp_path / "b")
    assert losses_b[first_resumed_step] == losses_a[first_resumed_step]
    assert losses_b == losses_a
    final_a = checkpoint.load_checkpoint(uninterrupted["last_checkpoint"])["model"]
    final_b = checkpoint.load_checkpoint(resumed["last_checkpoint"])["model"]
    for name, value in final_a.items():
        torch.testing.assert_close(final_b[name], value, rtol=0, atol=0)


def test_a_kill_between_the_two_checkpoints_of_an_epoch_changes_nothing(tmp_path, monkeypatch):
    uninterrupted = loop.train(tiny_config(tmp_path / "a"))
    best_epoch = uninterrupted["metrics"]["best_epoch"]  # its end writes best.pt and last.pt
    original = loop.save_checkpoint
    written = []

    def save_then_die(state, path):
        original(state, path)
        written.append(Path(path).name)
        if state["progress"]["epoch"] == best_epoch:
            raise KeyboardInterrupt  # as a kill before the second file

    monkeypatch.setattr(loop, "save_checkpoint", save_then_die)
    with pytest.raises(KeyboardInterrupt):
        loop.train(tiny_config(tmp_path / "b"))
    monkeypatch.undo()
    assert written[-1] == "best.pt"
    resumed = loop.train(tiny_config(tmp_path / "b", "resume=true"))
    assert resumed["metrics"] == uninterrupted["metrics"]
    for name in ("best_checkpoint", "last_checkpoint"):
        final_a = checkpoint.load_checkpoint(uninterrupted[name])["model"]
        final_b = checkpoint.load_checkpoint(resumed[name])["model"]
        assert all(torch.equal(final_b[key], value) for key, value in final_a.items()), name


def test_resume_takes_the_checkpoint_config(tmp_path, monkeypatch):
    _interrupt_at(monkeypatch, 1)
    with pytest.raises(KeyboardInterrupt):
        loop.train(tiny_config(tmp_path, "optimizer.lr=1e-3"))
    monkeypatch.undo()
    with pytest.warns(UserWarning, match=r"ignored differences: \['optimizer.lr'\]"):
        result = loop.train(tiny_config(tmp_path, "optimizer.lr=5e-2", "resume=true"))
    assert checkpoint.load_checkpoint(result["last_checkpoint"])["config"]["optimizer"]["lr"] == 1e-3


def test_resume_true_without_a_checkpoint_starts_from_the_beginning(tmp_path):
    with pytest.warns(UserWarning, match=r"resume=true: no checkpoints/last\.pt in .*starting from the beginning"):
        assert resume.resume_checkpoint(True, tmp_path / "run", ["resume=true"]) is None


def test_resume_true_finds_the_newest_sibling_with_the_same_overrides(tmp_path):
    runs = (("old", ["seed=1"]), ("other", ["seed=2"]), ("new", ["seed=1", "resume=true"]))
    for age, (name, overrides) in enumerate(runs):
        run = tmp_path / name
        checkpoint.save_checkpoint({}, run / "checkpoints" / "last.pt")
        os.utime(run / "checkpoints" / "last.pt", (1000 + age, 1000 + age))
        (run / ".hydra").mkdir()
        (run / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    current = tmp_path / "current"
    found = resume.resume_checkpoint(True, current, ["seed=1", "resume=true"])
    assert found == tmp_path / "new" / "checkpoints" / "last.pt"
    assert resume.resume_checkpoint(True, current, ["seed=2"]).parent.parent.name == "other"
    changed_machine = ["trainer.num_workers=2", "seed=1", "trainer.threads=4", "resume=true"]
    assert resume.resume_checkpoint(True, current, changed_machine).parent.parent.name == "new"
    with pytest.warns(UserWarning, match="same overrides; starting from the beginning"):
        assert resume.resume_checkpoint(True, current, ["seed=3"]) is None
    assert resume.resume_checkpoint(False, current) is None


def test_the_scalar_log_drops_a_line_a_killed_process_left_unfinished(tmp_path):
    (tmp_path / "scalars.jsonl").write_text('{"step": 1, "train/loss": 2.0}\n{"step": 2, "train/lo')
    logger = RunLogger(tmp_path, tensorboard=False)
    logger.scalars({"loss": 1.5}, 2, prefix="train/")
    logger.close()
    assert [(r["step"], r["train/loss"]) for r in read_scalars(tmp_path)] == [(1, 2.0), (2, 1.5)]


def test_save_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / "last.pt"
    checkpoint.save_checkpoint({"value": torch.tensor(1.0)}, path)

    def broken_save(obj, handle):
        handle.write(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", broken_save)
    with pytest.raises(OSError, match="disk full"):
        checkpoint.save_checkpoint({"value": torch.tensor(2.0)}, path)
    monkeypatch.undo()
    assert float(checkpoint.load_checkpoint(path)["value"]) == 1.0
    assert [p.name for p in tmp_path.iterdir()] == ["last.pt"]


CORRUPTIONS = {
    "truncated": lambda data: data[: len(data) // 2],
    "empty": lambda data: b"",
    "garbage": lambda data: b"\x80\x02not a checkpoint at all" * 10,
}


def _corrupt(path: Path, how: str) -> None:
    path.write_bytes(CORRUPTIONS[how](path.read_bytes()))


@pytest.mark.parametrize("how", sorted(CORRUPTIONS))
def test_a_corrupt_checkpoint_is_named(tmp_path, how):
    path = checkpoint.save_checkpoint({"value": torch.zeros(1000)}, tmp_path / "last.pt")
    _corrupt(path, how)
    with pytest.raises(checkpoint.CorruptCheckpointError, match=rf"{re.escape(str(path))}: cannot read the checkpoint"):
        checkpoint.load_checkpoint(path)


@pytest.mark.parametrize("how", sorted(CORRUPTIONS))
def test_resume_falls_back_to_the_newest_readable_checkpoint(tmp_path, how):
    folder = tmp_path / "checkpoints"
    for age, (name, epoch) in enumerate((("old.pt", 1), ("best.pt", 2), ("last.pt", 3))):
        checkpoint.save_checkpoint({"progress": {"epoch": epoch}}, folder / name)
        os.utime(folder / name, (1000 + age, 1000 + age))
    _corrupt(folder / "last.pt", how)
    expected = rf"{re.escape(str(folder / 'last.pt'))}: cannot read.*resuming from .*best\.pt \(epoch 2\)"
    with pytest.warns(RuntimeWarning, match=expected):
        state = checkpoint.load_resume_checkpoint(tmp_path)
    assert state["path"] == str(folder / "best.pt")
    _corrupt(folder / "best.pt", "empty")
    _corrupt(folder / "old.pt", "garbage")
    with pytest.raises(checkpoint.CorruptCheckpointError, match=r"no readable checkpoint(.|\n)*last\.pt(.|\n)*best"):
        checkpoint.load_resume_checkpoint(folder / "last.pt")


def test_training_resumes_from_best_when_last_is_corrupt(tmp_path, monkeypatch):
    _interrupt_at(monkeypatch, 2)
    with pytest.raises(KeyboardInterrupt):
        loop.train(tiny_config(tmp_path))
    monkeypatch.undo()
    last = tmp_path / "checkpoints" / "last.pt"
    best_epoch = checkpoint.load_checkpoint(tmp_path / "checkpoints" / "best.pt")["progress"]["epoch"]
    _corrupt(last, "truncated")
    expected = rf"{re.escape(str(last))}: cannot read the checkpoint.*resuming from .*best\.pt"
    with pytest.warns(RuntimeWarning, match=expected):
        result = loop.train(tiny_config(tmp_path, "resume=true"))
    final = checkpoint.load_checkpoint(result["last_checkpoint"])
    assert final["progress"]["epoch"] == 3 > best_epoch


def test_evaluate_names_a_corrupt_checkpoint(tmp_path, hydra_compose):
    path = checkpoint.save_checkpoint({"value": torch.zeros(100)}, tmp_path / "best.pt")
    _corrupt(path, "truncated")
    cfg = hydra_compose("evaluate", [f"paths.root_dir={ROOT}", f"checkpoint={path}", "device=cpu"])
    with pytest.raises(checkpoint.CorruptCheckpointError, match=rf"{re.escape(str(path))}: cannot read the checkpoint"):
        evaluate(cfg)


def _dead_pid() -> int:
    """The id of a process that has exited."""
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


def test_save_removes_temporaries_of_dead_writers(tmp_path):
    orphan = tmp_path / f".last.pt.{_dead_pid()}.tmp"
    orphan.write_bytes(b"x" * 100)
    alive = tmp_path / f".best.pt.{os.getppid()}.tmp"
    alive.write_bytes(b"being written")
    unrelated = tmp_path / ".notes.tmp"
    unrelated.write_text("kept")
    checkpoint.save_checkpoint({}, tmp_path / "last.pt")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([alive.name, unrelated.name, "last.pt"])


def test_save_fsyncs_the_folder_after_the_rename(tmp_path, monkeypatch):
    synced = []
    original = os.fsync

    def recording_fsync(descriptor):
        synced.append(("folder" if stat.S_ISDIR(os.fstat(descriptor).st_mode) else "file", os.listdir(tmp_path)))
        original(descriptor)

    monkeypatch.setattr(os, "fsync", recording_fsync)
    checkpoint.save_checkpoint({}, tmp_path / "last.pt")
    assert [kind for kind, _ in synced] == ["file", "folder"]
    assert synced[-1][1] == ["last.pt"]


def test_load_rejects_foreign_files(tmp_path):
    torch.save({"state_dict": {}}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not a linereg checkpoint"):
        checkpoint.load_checkpoint(tmp_path / "other.pt")
    with pytest.raises(FileNotFoundError):
        checkpoint.load_checkpoint(tmp_path / "missing.pt")


def test_find_checkpoint_in_a_run_folder(tmp_path):
    for name in ("last.pt", "best.pt"):
        checkpoint.save_checkpoint({}, tmp_path / "checkpoints" / name)
    assert checkpoint.find_checkpoint(tmp_path).name == "best.pt"
    assert checkpoint.find_checkpoint(tmp_path, prefer=("last.pt",)).name == "last.pt"


def test_find_checkpoint_follows_the_runs_own_evaluation(tmp_path):
    for name in ("last.pt", "best.pt"):
        checkpoint.save_checkpoint({}, tmp_path / "checkpoints" / name)
    metrics = tmp_path / "metrics.json"
    metrics.write_text(json.dumps({"evaluated_checkpoint": {"file": "last.pt", "epoch": 6}}))
    assert checkpoint.find_checkpoint(tmp_path).name == "last.pt"
    assert checkpoint.find_checkpoint(tmp_path, prefer=("best.pt",)).name == "best.pt"
    metrics.write_text("{not json")
    assert checkpoint.find_checkpoint(tmp_path).name == "best.pt"


def test_training_randomness_is_a_function_of_the_position():
    loss = build_loss({"terms": {"a": {"name": "line_intersection", "seed": 3}, "b": {"name": "line_intersection"}}})
    generators = randomness.loss_generators(loss)
    assert sorted(generators) == ["parts.a.generator", "parts.b.generator"]

    def draws(epoch, batch, rank=0):
        randomness.seed_training_step(loss, 7, epoch, batch, rank)
        return [random.random(), np.random.rand(), float(torch.rand(1))] + [  # noqa: NPY002
            float(torch.rand(1, generator=g)) for g in generators.values()
        ]

    first = draws(2, 5)
    draws(0, 0)
    torch.rand(100)
    assert draws(2, 5) == first  # whatever ran before
    assert len(set(first[3:])) == 2  # each generator its own stream
    for other in (draws(2, 6), draws(3, 5), draws(2, 5, rank=1)):
        assert set(other).isdisjoint(first)


def test_evaluation_draws_the_same_lines_each_time():
    loss = build_loss({"name": "line_intersection"})
    randomness.seed_evaluation(loss, 0)
    first = torch.rand(3, generator=loss.generator)
    torch.rand(3, generator=loss.generator)
    randomness.seed_evaluation(loss, 0)
    assert torch.equal(torch.rand(3, generator=loss.generator), first)
