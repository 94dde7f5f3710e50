"""PyTorch DDP plumbing for ``torchrun``: process group, device per rank, collective flags.

``torchrun --nproc-per-node N -m relocdepth.cli train ...`` sets RANK / WORLD_SIZE / LOCAL_RANK;
gloo on CPU, nccl on CUDA. A single process (no WORLD_SIZE) needs none of it.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
from dataclasses import dataclass
from typing import Any

from relocdepth.errors import UserError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Dist:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


DEVICE_CHOICES = ("auto", "cpu", "cuda", "cuda:N")
_DEVICE_RE = re.compile(r"auto|cpu|cuda(:\d+)?")


def check_device(name: str) -> str:
    """The one ``--device`` grammar: ``auto``, ``cpu``, ``cuda`` or ``cuda:N``; UserError otherwise."""
    text = str(name).strip().lower()
    if not _DEVICE_RE.fullmatch(text):
        raise UserError(f"--device must be one of {', '.join(DEVICE_CHOICES)} (N: a GPU index), "
                        f"not {name!r}")
    return text


def pick_device(name: str, local_rank: int = 0) -> Any:
    """``auto`` -> CUDA when available, else CPU; ``cuda`` -> GPU ``local_rank``; ``cuda:N`` -> GPU N.

    Asking for a GPU this torch does not see is a user error, said before anything runs.
    """
    import torch

    name = check_device(name)
    if name == "cpu" or (name == "auto" and not torch.cuda.is_available()):
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise UserError(f"--device {name} but this torch sees no CUDA GPU; use --device cpu or auto")
    index = int(name.split(":")[1]) if ":" in name else local_rank
    if index >= torch.cuda.device_count():
        raise UserError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA GPU(s) "
                        f"(cuda:0 to cuda:{torch.cuda.device_count() - 1})")
    return torch.device("cuda", index)


def init_distributed(device_name: str) -> tuple[Dist, Any]:
    """Join the torchrun process group if there is one; returns (Dist, torch.device)."""
    import torch
    import torch.distributed as dist

    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Dist(), pick_device(device_name)
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    if ":" in check_device(device_name):
        raise UserError(f"--device {device_name} names one GPU, but under torchrun each rank uses "
                        "its own (cuda:LOCAL_RANK); give --device cuda or auto")
    device = pick_device(device_name, local)
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
    log.info("DDP rank %d of %d on %s", rank, world, device)
    return Dist(rank, world, local), device


def shutdown_distributed(d: Dist) -> None:
    import torch.distributed as dist

    if d.enabled and dist.is_initialized():
        dist.destroy_process_group()


def any_rank(d: Dist, flags: list[bool], device: Any) -> list[bool]:
    """Element-wise OR of boolean flags over all ranks (identity in one process)."""
    if not d.enabled:
        return flags
    return [v > 0 for v in max_over_ranks(d, [float(f) for f in flags], device)]


def max_over_ranks(d: Dist, values: list[float], device: Any) -> list[float]:
    """Element-wise maximum of numbers over all ranks (identity in one process)."""
    if not d.enabled:
        return values
    import torch
    import torch.distributed as dist

    t = torch.tensor([float(v) for v in values], dtype=torch.float64, device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return t.tolist()


def barrier(d: Dist) -> None:
    if d.enabled:
        import torch.distributed as dist

        dist.barrier()


def broadcast_buffers(d: Dist, module: Any) -> None:
    """Copy rank 0's buffers (BatchNorm running statistics) to every rank.

    DDP broadcasts them at the start of each forward, after which every rank updates its copy with
    its own batch; so after the last step the ranks differ by that step's update unless this runs.
    """
    if not d.enabled:
        return
    import torch.distributed as dist

    for b in module.buffers():
        dist.broadcast(b.data, src=0)


def parameter_digest(module: Any) -> str:
    """sha256 over every parameter's bytes (in name order): equal on all DDP ranks."""
    import torch

    h = hashlib.sha256()
    for name, p in sorted(module.named_parameters()):
        h.update(name.encode())
        h.update(p.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()
