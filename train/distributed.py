"""Devices, data loaders and DistributedDataParallel.

``torchrun --nproc_per_node=K -m train ...`` starts ``K`` processes; each reads ``RANK``,
``WORLD_SIZE`` and ``LOCAL_RANK`` from the environment, joins the process group (NCCL on CUDA,
gloo on CPU) and trains on its shard of every epoch. Rank 0 alone validates, logs, writes
checkpoints and prints; the other ranks wait for it. Under Slurm (``launcher=slurm`` with
``tasks_per_node > 1``) the same variables come from submitit.

Hydra runs in every process; the other ranks get ``hydra.output_subdir=null`` and a throw-away
run folder (:func:`hydra_rank_overrides`), so only rank 0's run folder holds files.
"""

from __future__ import annotations

import contextlib
import functools
import os
import tempfile
import warnings
from dataclasses import dataclass, field, replace
from typing import Any

import numba
import torch
import torch.distributed as dist
from torch import nn
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, Dataset, DistributedSampler

from linereg.datasets import collate_pairs
from linereg.structures import RegistrationOutput
from linereg.train.randomness import loader_generator

AMP_DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}


@dataclass(frozen=True)
class DistContext:
    """This process's place in the job.

    Attributes:
        rank: global rank (0 when not distributed).
        world_size: number of processes.
        local_rank: rank on this machine (selects the GPU).
        device: the device this process computes on.
    """

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def resolve_device(spec: str, local_rank: int = 0, *, name: str = "trainer.device") -> torch.device:
    """The device named by ``spec``: ``auto`` (CUDA when available), ``cpu``, ``cuda``, ``cuda:N``.

    Under DDP a bare ``cuda`` (or ``auto``) means the GPU of this process's local rank.

    Raises:
        ValueError: ``spec`` is not a device name, or names CUDA on a machine without it (or a GPU
            index it does not have); the message names the setting ``name``.
    """
    if spec == "auto":
        spec = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(spec)
    except (RuntimeError, TypeError) as error:
        raise ValueError(f"{name}={spec!r} is not a device; use auto, cpu, cuda or cuda:N ({error})") from error
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(
                f"{name}={spec!r} but CUDA is not available on this machine (torch {torch.__version__}, "
                f"CUDA build: {torch.version.cuda or 'no'}); use {name}=cpu, or {name}=auto to take a GPU only "
                "when there is one"
            )
        if device.index is None:
            device = torch.device("cuda", local_rank)
        if device.index >= torch.cuda.device_count():
            raise ValueError(
                f"{name}={spec!r}: this machine has {torch.cuda.device_count()} CUDA device(s), "
                f"cuda:0 to cuda:{torch.cuda.device_count() - 1}"
            )
    return device


def set_threads(threads: int | None) -> None:
    """Compute with ``threads`` CPU threads in torch and in the loss's numba kernels (``None``:
    torch's default, all cores), capped at numba's pool (``NUMBA_NUM_THREADS``).

    Both counts are set to the same value because numba's OpenMP threading layer sets the OpenMP
    thread count of its caller to its own at each parallel call: torch would otherwise compute
    with one count before the process's first loss evaluation and another after it, and a run
    resumed in a new process would differ in the last bits from the uninterrupted one. One thread
    per process avoids the heavy slowdown of OpenMP thread pools on an oversubscribed CPU.
    """
    if threads is not None and threads < 1:
        raise ValueError(f"trainer.threads must be >= 1 or null, got {threads}")
    count = min(torch.get_num_threads() if threads is None else threads, numba.config.NUMBA_NUM_THREADS)
    torch.set_num_threads(count)
    numba.set_num_threads(count)


def _export_slurm_environment() -> None:
    """Set RANK/WORLD_SIZE/... from a multi-task Slurm job started by submitit."""
    if "RANK" in os.environ or int(os.environ.get("SLURM_NTASKS", "1")) <= 1:
        return
    try:
        from submitit.helpers import TorchDistributedEnvironment
    except ImportError:
        return
    TorchDistributedEnvironment().export(set_cuda_visible_devices=False)


def setup(device_spec: str = "auto") -> DistContext:
    """Join the process group when launched by torchrun or Slurm; otherwise a single process."""
    _export_slurm_environment()
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size <= 1:
        return DistContext(device=resolve_device(device_spec))
    rank, local_rank = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    device = resolve_device(device_spec, local_rank)
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
    return DistContext(rank=rank, world_size=world_size, local_rank=local_rank, device=device)


def teardown(ctx: DistContext) -> None:
    """Leave the process group (no-op for a single process).

    Free every DistributedDataParallel wrapper first (the trainer does so when it finishes). A
    wrapper's reducer holds the group; freed after this call, it would run the group's destructor
    with the GIL held, which waits for gloo's worker threads while one of them waits for the GIL
    to drop its last collective: the process hangs at exit.
    """
    if ctx.enabled and dist.is_initialized():
        dist.destroy_process_group()


def hydra_rank_overrides() -> list[str]:
    """Extra Hydra overrides for ranks other than 0: no run folder of their own."""
    if int(os.environ.get("RANK", "0")) == 0:
        return []
    scratch = os.path.join(tempfile.gettempdir(), f"linereg-rank{os.environ['RANK']}")
    return ["hydra.output_subdir=null", f"hydra.run.dir={scratch}", "hydra/job_logging=disabled"]


def barrier(ctx: DistContext) -> None:
    """Wait for every rank."""
    if ctx.enabled:
        dist.barrier()


def broadcast_object(value: Any, ctx: DistContext) -> Any:
    """Rank 0's ``value`` on every rank."""
    if not ctx.enabled:
        return value
    box = [value]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def all_ranks_true(flag: bool, ctx: DistContext) -> bool:
    """Whether ``flag`` holds on every rank (all ranks must agree to skip a step together)."""
    if not ctx.enabled:
        return flag
    value = torch.tensor([1 if flag else 0], device=ctx.device)
    dist.all_reduce(value, op=dist.ReduceOp.MIN)
    return bool(value.item())


def wrap(model: nn.Module, ctx: DistContext, *, find_unused_parameters: bool = False) -> nn.Module:
    """``model`` wrapped in DistributedDataParallel when distributed, else unchanged."""
    if not ctx.enabled:
        return model
    device_ids = [ctx.device.index] if ctx.device.type == "cuda" else None
    return DistributedDataParallel(model, device_ids=device_ids, find_unused_parameters=find_unused_parameters)


def unwrap(model: nn.Module) -> nn.Module:
    """The model inside a DistributedDataParallel wrapper (or the model itself)."""
    return model.module if isinstance(model, DistributedDataParallel) else model


def make_loader(
    dataset: Dataset,
    *,
    batch_size: int,
    num_points: int | None,
    shuffle: bool,
    seed: int = 0,
    epoch: int = 0,
    num_workers: int = 0,
    ctx: DistContext | None = None,
    skip_batches: int = 0,
) -> DataLoader:
    """A loader of :class:`~linereg.structures.PairBatch` es over this rank's shard.

    The order and the workers' seeds are pure functions of ``(seed, epoch, rank)``, so a resumed
    run sees the same batches as an uninterrupted one.

    Args:
        dataset: pairs.
        batch_size: pairs per batch (per process).
        num_points: points per cloud after collation (``None``: pad).
        shuffle: shuffle (training) or keep the order (evaluation).
        seed: shuffling seed.
        epoch: epoch number (changes the shuffle).
        num_workers: loader worker processes.
        ctx: distributed context (``None``: one process, the whole dataset).
        skip_batches: leave out the epoch's first batches (those a resumed step checkpoint ran).
    """
    ctx = ctx or DistContext()
    sampler = DistributedSampler(
        dataset, num_replicas=ctx.world_size, rank=ctx.rank, shuffle=shuffle, seed=seed, drop_last=False
    )
    sampler.set_epoch(epoch)
    return DataLoader(
        dataset,
        batch_size=batch_size,
        sampler=list(sampler)[skip_batches * batch_size :],
        num_workers=num_workers,
        collate_fn=functools.partial(collate_pairs, num_points=num_points),
        pin_memory=ctx.device.type == "cuda",
        persistent_workers=False,
        generator=loader_generator(seed, epoch, ctx.rank),
    )


def amp_dtype(amp: str | bool | None, device: torch.device) -> torch.dtype | None:
    """The autocast dtype for ``trainer.amp`` (``false``, ``bf16`` or ``fp16``); ``None`` when off.

    Mixed precision runs only on CUDA; elsewhere it is switched off with a warning.
    """
    if amp in (None, False, "false", "none"):
        return None
    if amp not in AMP_DTYPES:
        raise ValueError(f"trainer.amp must be false, 'bf16' or 'fp16', got {amp!r}")
    if device.type != "cuda":
        warnings.warn(f"trainer.amp={amp!r} needs CUDA; running in float32 on {device}", stacklevel=2)
        return None
    return AMP_DTYPES[amp]


def autocast(device: torch.device, dtype: torch.dtype | None) -> contextlib.AbstractContextManager:
    """Autocast context for the model forward (a no-op when ``dtype`` is ``None``)."""
    if dtype is None:
        return contextlib.nullcontext()
    return torch.autocast(device_type=device.type, dtype=dtype)


def _float32(value: Any) -> Any:
    """Floating tensors (also inside lists, tuples and dicts) cast to float32."""
    if isinstance(value, torch.Tensor):
        return value.float() if value.is_floating_point() else value
    if isinstance(value, list | tuple):
        return type(value)(_float32(item) for item in value)
    if isinstance(value, dict):
        return {key: _float32(item) for key, item in value.items()}
    return value


def float32_output(output: RegistrationOutput) -> RegistrationOutput:
    """The model output in float32: losses and Procrustes-based metrics run in full precision."""
    return replace(output, transforms=_float32(output.transforms), extras=_float32(output.extras))
