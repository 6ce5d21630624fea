"""DistributedDataParallel on the CPU: two gloo processes train one tiny run together."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp

from linereg.train import distributed

ROOT = Path(__file__).resolve().parent.parent


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _worker(rank: int, world_size: int, port: int, output_dir: str, results: str) -> None:
    """One DDP process: the environment torchrun would set, then ``train(cfg)``."""
    os.environ.update(
        {
            "MASTER_ADDR": "127.0.0.1",
            "MASTER_PORT": str(port),
            "RANK": str(rank),
            "LOCAL_RANK": str(rank),
            "WORLD_SIZE": str(world_size),
        }
    )
    from hydra import compose, initialize_config_dir

    from linereg.train.loop import train

    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
        cfg = compose(
            "train",
            overrides=[
                "debug=tiny",
                f"paths.root_dir={ROOT}",
                f"paths.output_dir={output_dir}",
                "model.num_neighbors=8",
                "loss.num_lines=300",
                "curriculum=none",
                "curriculum.stages.full.epochs=1",
            ],
        )
    result = train(cfg)
    torch.save(
        {name: value.detach().clone() for name, value in result["model"].state_dict().items()},
        Path(results) / f"rank{rank}.pt",
    )


def test_two_process_gloo_step(tmp_path):
    output_dir, results = tmp_path / "run", tmp_path / "results"
    results.mkdir()
    mp.spawn(_worker, args=(2, _free_port(), str(output_dir), str(results)), nprocs=2, join=True)
    rank0, rank1 = (torch.load(results / f"rank{r}.pt") for r in (0, 1))
    for name, value in rank0.items():
        torch.testing.assert_close(rank1[name], value, rtol=0, atol=0, msg=f"{name} differs between ranks")
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
