"""A training run killed with SIGKILL (mid-epoch, inside a checkpoint write) and resumed in new
processes ends exactly as its uninterrupted twin: same per-step losses, validation figures and
final weights.

The kills come from the test-only switch ``LINEREG_KILL_AT`` (:mod:`linereg.train.faults`).
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
from pathlib import Path

import torch

from linereg.checkpoint import load_checkpoint
from linereg.train.faults import ENVIRONMENT_VARIABLE
from linereg.train.logging import read_scalars

# Four epochs of debug=tiny on 6 training pairs, batches of 2: the stages easy (epoch 1: step 1),
# subset (epoch 2: steps 2-3) and full (epochs 3-4: steps 4-6 and 7-9).
RUN = [
    "debug=tiny",
    "model.num_neighbors=8",
    "loss.num_lines=300",
    "dataset.splits.train.num_shapes=3",
    "curriculum.stages.full.epochs=2",
    "trainer.max_steps_per_epoch=null",
]


def _start(run_dir: Path, *overrides: str, kill_at: str | None = None) -> subprocess.Popen:
    """Start ``python -m linereg.train`` in a new process (to be killed at ``kill_at``)."""
    env = {key: value for key, value in os.environ.items() if key != ENVIRONMENT_VARIABLE}
    if kill_at is not None:
        env[ENVIRONMENT_VARIABLE] = kill_at
    run_dir.mkdir(parents=True, exist_ok=True)
    return subprocess.Popen(
        [sys.executable, "-m", "linereg.train", *RUN, *overrides, f"hydra.run.dir={run_dir}"],
        cwd=run_dir.parent,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def _exit_code(process: subprocess.Popen) -> int:
    """The exit code of a training process (SIGKILL or success; anything else fails the test)."""
    _, stderr = process.communicate(timeout=300)
    if process.returncode not in (0, -signal.SIGKILL):
        raise AssertionError(stderr[-3000:])
    return process.returncode


def _train(run_dir: Path, *overrides: str, kill_at: str | None = None) -> int:
    """Run ``python -m linereg.train`` in a new process (killed at ``kill_at``); its exit code."""
    return _exit_code(_start(run_dir, *overrides, kill_at=kill_at))


def _last_records(run_dir: Path, tag: str) -> dict[int, float]:
    """``{step: value of tag}``, the last record of each step winning (a resumed run logs again)."""
    return {record["step"]: record[tag] for record in read_scalars(run_dir) if tag in record}


def _position(run_dir: Path) -> tuple[int, int, int]:
    """``(epoch, batch, global step)`` that the run's ``last.pt`` continues from."""
    progress = load_checkpoint(run_dir / "checkpoints" / "last.pt")["progress"]
    return progress["epoch"], progress["batch"], progress["global_step"]


def test_a_run_killed_anywhere_resumes_exactly_in_new_processes(tmp_path):
    twin, killed = tmp_path / "twin", tmp_path / "killed"
    uninterrupted = _start(twin)  # beside the killed run's processes, on the other core

    # Killed mid-epoch in the first epoch of "full": last.pt is the end of "subset" (a stage boundary).
    first_kill = random.choice([4, 5, 6])
    assert _train(killed, kill_at=f"step:{first_kill}") == -signal.SIGKILL
    assert _position(killed) == (2, 0, 3)
    # Resumed with a loader worker and a checkpoint every step, killed inside the second write
    # (step 5's): last.pt stays whole, at step 4 (the middle of an epoch and of a stage).
    resumed = ["resume=true", "trainer.num_workers=1", "trainer.checkpoint_every_steps=1"]
    assert _train(killed, *resumed, kill_at="checkpoint:2") == -signal.SIGKILL
    assert _position(killed) == (2, 1, 4)
    assert [path.name for path in (killed / "checkpoints").glob(".last.pt.*.tmp")]  # the killed write's
    # Killed in the last epoch, inside the stage: resumed from the end of epoch 3 or from step 8.
    third_kill = random.choice([7, 8, 9])
    every_second_step = ["resume=true", "trainer.checkpoint_every_steps=2"]
    assert _train(killed, *every_second_step, kill_at=f"step:{third_kill}") == -signal.SIGKILL
    assert _train(killed, "resume=true") == 0
    assert _exit_code(uninterrupted) == 0

    context = f"killed at step {first_kill}, in a checkpoint write at step 5, at step {third_kill}"
    for tag in ("train/loss", "train/grad_norm/total", "epoch/loss", "val/err_r_deg_mean", "val/loss"):
        expected = _last_records(twin, tag)
        assert expected and _last_records(killed, tag) == expected, (tag, context)
    assert max(_last_records(killed, "train/loss")) == 9
    metrics = [json.loads((run / "metrics.json").read_text())["metrics"] for run in (twin, killed)]
    assert metrics[1] == metrics[0], context  # validation, initial validation, test, best epoch
    for name in ("last.pt", "best.pt"):
        weights = [load_checkpoint(run / "checkpoints" / name)["model"] for run in (twin, killed)]
        for key, value in weights[0].items():
            assert torch.equal(weights[1][key], value), (name, key, context)
    assert not list((killed / "checkpoints").glob(".*.tmp"))
