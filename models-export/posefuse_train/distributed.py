"""Several processes, one run: PyTorch's own DistributedDataParallel, started by `torchrun`.

Every process draws the same global batch (same seeds, same sampler) and trains on its slice of
it; DDP averages the gradients, so with equal slices a step is the one-process step at the same
global batch up to the order of floating-point sums, and on the CPU BatchNorm statistics (see
`wrap`). Rank 0 alone writes checkpoints, logs and the bundle.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist


@dataclass(frozen=True)
class Dist:
    rank: int = 0
    world: int = 1

    @property
    def main(self) -> bool:
        return self.rank == 0

    def slice(self, n: int) -> slice:
        """This process's rows of a global batch of n (contiguous, equal when world divides n)."""
        per = -(-n // self.world)
        return slice(min(n, self.rank * per), min(n, (self.rank + 1) * per))

    def mean(self, value: torch.Tensor) -> float:
        """The mean of a scalar over the processes (the loss every process logs)."""
        if self.world == 1:
            return float(value.detach())
        t = value.detach().float().reshape(1).clone()
        dist.all_reduce(t)
        return float(t) / self.world

    def barrier(self) -> None:
        if self.world > 1:
            dist.barrier()


def from_env(device: str) -> Dist:
    """Joins the process group torchrun describes (WORLD_SIZE > 1), else a single process.
    NCCL on CUDA, gloo on the CPU."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Dist()
    if not dist.is_initialized():
        backend = "nccl" if device.startswith("cuda") else "gloo"
        dist.init_process_group(backend=backend)
    return Dist(rank=dist.get_rank(), world=dist.get_world_size())


def local_device(device: str) -> str:
    """cuda under torchrun means this process's GPU (LOCAL_RANK)."""
    if device == "cuda" and "LOCAL_RANK" in os.environ:
        return f"cuda:{int(os.environ['LOCAL_RANK'])}"
    return device


def wrap(net: torch.nn.Module, d: Dist, device: str) -> torch.nn.Module:
    """The network DDP trains (the same module when single-process). On CUDA its BatchNorm layers
    are synchronised (SyncBatchNorm), so every process normalises with the global batch's
    statistics; PyTorch has no SyncBatchNorm on the CPU, where each process normalises its slice.
    The layers are replaced inside `net`, whose state_dict keeps its keys."""
    if d.world == 1:
        return net
    if device.startswith("cuda"):
        net = torch.nn.SyncBatchNorm.convert_sync_batchnorm(net)
    ids = [torch.device(device).index] if device.startswith("cuda") else None
    return torch.nn.parallel.DistributedDataParallel(net, device_ids=ids)


def shutdown() -> None:
    if dist.is_initialized():
        dist.destroy_process_group()
