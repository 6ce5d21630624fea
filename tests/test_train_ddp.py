"""DistributedDataParallel on the CPU: two gloo processes train one tiny run together."""

from __future__ import annotations

import datetime
import faulthandler
import gc
import os
import socket
import sys
import time
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp
from torch.nn.parallel import DistributedDataParallel

from linereg.train import distributed

ROOT = Path(__file__).resolve().parent.parent
# The two-process run takes about 15 s. A collective that waits longer than COLLECTIVE_TIMEOUT
# raises; a rank still alive after RANK_DEADLINE prints every thread's stack and exits; the test
# kills what is left after TEST_DEADLINE. A hang therefore fails in minutes, says where it
# waited, and leaves no process behind to keep pytest from exiting.
COLLECTIVE_TIMEOUT = datetime.timedelta(seconds=120)
RANK_DEADLINE = 180.0
TEST_DEADLINE = 240.0


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _worker(rank: int, world_size: int, port: int, output_dir: str, results: str) -> None:
    """One DDP process: the environment torchrun would set, then ``train(cfg)``."""
    faulthandler.dump_traceback_later(RANK_DEADLINE, exit=True, file=sys.stderr)
    os.environ.update(
        {
            "MASTER_ADDR": "127.0.0.1",
            "MASTER_PORT": str(port),
            "RANK": str(rank),
            "LOCAL_RANK": str(rank),
            "WORLD_SIZE": str(world_size),
        }
    )
    import torch.distributed as dist

    # ``distributed.setup`` joins an initialised group as it is; this one's collectives time out.
    dist.init_process_group("gloo", rank=rank, world_size=world_size, timeout=COLLECTIVE_TIMEOUT)

    from linereg.train.loop import train
    from tests.conftest import compose_config

    cfg = compose_config(
        "train",
        [
            "debug=tiny",
            f"paths.root_dir={ROOT}",
            f"paths.output_dir={output_dir}",
            "model.num_neighbors=8",
            "loss.num_lines=300",
            "curriculum=none",
            "curriculum.stages.full.epochs=1",
        ],
    )
    # A DistributedDataParallel wrapper freed after the group is destroyed can hang the process at
    # exit (distributed.teardown); record whether one is still alive when the group goes.
    wrappers_at_teardown = []
    destroy = dist.destroy_process_group

    def destroy_and_record(*args, **kwargs):
        gc.collect()
        wrappers_at_teardown.append(sum(isinstance(item, DistributedDataParallel) for item in gc.get_objects()))
        destroy(*args, **kwargs)

    dist.destroy_process_group = destroy_and_record
    result = train(cfg)
    state = {name: value.detach().clone() for name, value in result["model"].state_dict().items()}
    torch.save({"state": state, "wrappers_at_teardown": wrappers_at_teardown}, Path(results) / f"rank{rank}.pt")


def test_two_process_gloo_step(tmp_path):
    output_dir, results = tmp_path / "run", tmp_path / "results"
    results.mkdir()
    context = mp.start_processes(
        _worker, args=(2, _free_port(), str(output_dir), str(results)), nprocs=2, join=False, daemon=True
    )
    deadline = time.monotonic() + TEST_DEADLINE
    while not context.join(timeout=5):
        if time.monotonic() > deadline:
            for process in context.processes:
                process.kill()
            pytest.fail(f"the two gloo ranks did not finish within {TEST_DEADLINE:.0f} s (their stacks are on stderr)")
    rank0, rank1 = (torch.load(results / f"rank{r}.pt") for r in (0, 1))
    for name, value in rank0["state"].items():
        torch.testing.assert_close(rank1["state"][name], value, rtol=0, atol=0, msg=f"{name} differs between ranks")
    assert rank0["wrappers_at_teardown"] == rank1["wrappers_at_teardown"] == [0]
    checkpoint = torch.load(output_dir / "checkpoints" / "last.pt", weights_only=True)
    # 4 training pairs, 2 per rank and batch: one synchronised step per epoch.
    assert checkpoint["progress"]["global_step"] == 1
    assert (output_dir / "metrics.json").is_file()


def test_single_process_context():
    ctx = distributed.setup("cpu")
    assert (ctx.rank, ctx.world_size, ctx.is_main, ctx.enabled) == (0, 1, True, False)
    model = torch.nn.Linear(2, 2)
    assert distributed.wrap(model, ctx) is model and distributed.unwrap(model) is model
    assert distributed.broadcast_object({"a": 1}, ctx) == {"a": 1}
    assert distributed.all_ranks_true(False, ctx) is False


def test_hydra_overrides_for_other_ranks(monkeypatch):
    monkeypatch.setenv("RANK", "0")
    assert distributed.hydra_rank_overrides() == []
    monkeypatch.setenv("RANK", "1")
    assert "hydra.output_subdir=null" in distributed.hydra_rank_overrides()


@pytest.mark.parametrize("spec", ["cuda", "cuda:1"])
def test_cuda_request_without_cuda_is_explained(monkeypatch, spec):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match=rf"trainer.device='{spec}' but CUDA is not available.*trainer.device=cpu"):
        distributed.resolve_device(spec)
    assert distributed.resolve_device("auto").type == "cpu"


def test_unknown_device_names_the_setting():
    with pytest.raises(ValueError, match=r"device='gpu' is not a device; use auto, cpu, cuda or cuda:N"):
        distributed.resolve_device("gpu", name="device")
