"""Data-parallel training on several processes: `torchrun --nproc-per-node N -m gsmn.cli train supervised ...`
(docs/scale.md).

torchrun starts N copies of the command and tells each its rank (RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR,
MASTER_PORT); `init` joins them into one process group, NCCL where training runs on CUDA (rank r on
cuda:LOCAL_RANK), gloo on CPUs. Every rank holds the same model (built from the same seed, or read from the same
saved state) and takes the same global batches of the epoch (`train.batch_size` episodes, shuffled by the seed);
rank r reads only episodes r, r + N, r + 2N, ... of each. Each rank's loss on its shard is weighted by its share
of the global batch and the gradients averaged over the ranks (one all-reduce after the backward pass), so one
step optimises

    sum_r (n_r / n) L(shard_r)        (n_r episodes of the n in the global batch on rank r)

and every rank applies the same update. With N = 1 that is the one-process loss; with N > 1 it is the episode-
weighted mean of the shards' losses, each a mean over its own frames (`gsmn.model.losses`), so a global batch
split over ranks is not the same sum as the one loss of the concatenated batch (the frames are weighted per
shard, not over the batch). Each shard's random draws (dropout, pose noise, sampled negatives) are seeded from
the batch and the rank; the mirror draws from the batch, per episode, as on one process.

Rank 0 alone validates, writes the log, progress, checkpoint and saved state; the others wait for it. Whether to
save after a batch is rank 0's decision, sent to all, so all ranks stop and resume at the same batch: a killed
run resumes from its saved state as on one process (with any number of ranks).

The gradients are averaged by hand (`average_gradients`: one flat all-reduce per step) rather than by wrapping
the model in torch's DistributedDataParallel: the loss heads are called outside the model's forward, which that
wrapper's gradient hooks do not allow for; the arithmetic is the same as its averaging.
"""

from __future__ import annotations

import datetime
import faulthandler
import os
from dataclasses import dataclass

import numpy as np
import torch
import torch.distributed as dist


@dataclass(frozen=True)
class World:
    rank: int = 0
    size: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        return self.rank == 0

    def shard(self, keys: list) -> tuple[list, float]:
        """This rank's episodes of a global batch and its loss weight (N n_r / n, which the averaging over ranks
        makes n_r / n). A rank with no episode of a short last batch computes on the batch's first with weight 0:
        every rank must take part in the all-reduce."""
        mine = keys[self.rank::self.size]
        if not mine:
            return keys[:1], 0.0
        return mine, self.size * len(mine) / len(keys)

    def positions(self, count: int) -> list[int]:
        """The positions in a global batch of `count` episodes that this rank trains on (see `shard`)."""
        return list(range(self.rank, count, self.size)) or [0]


SINGLE = World()


def from_environment() -> World:
    """The rank torchrun gave this process (SINGLE without torchrun)."""
    size = int(os.environ.get("WORLD_SIZE", "1"))
    if size <= 1:
        return SINGLE
    return World(int(os.environ["RANK"]), size, int(os.environ.get("LOCAL_RANK", "0")))


def init(device: str) -> World:
    """Join torchrun's process group (once) for training on `device` ('cpu', 'cuda', 'cuda:N'); returns this
    process's World. Collecting DAgger rollouts on rank 0 may take long: the others wait up to a day."""
    world = from_environment()
    if world.size > 1 and not dist.is_initialized():
        # a rank that dies of a signal (as a gloo rank aborted at the end of a run: docs/scale.md) prints where each
        # of its Python threads was, into torchrun's report of the failure
        faulthandler.enable(all_threads=True)
        backend = "nccl" if device.startswith("cuda") else "gloo"
        if backend == "nccl":
            torch.cuda.set_device(world.local_rank)
        dist.init_process_group(backend, timeout=datetime.timedelta(hours=24))
    return world


def device_for(world: World, device: str) -> str:
    """Rank r trains on cuda:LOCAL_RANK where the config says CUDA (one GPU a process); CPUs as they are."""
    return f"cuda:{world.local_rank}" if world.size > 1 and device.startswith("cuda") else device


def rank_seed(seed: int, world: World) -> int:
    """The seed of this rank's shard of a batch seeded `seed` (one process: the batch's own)."""
    if world.size <= 1:
        return seed
    return int(np.random.SeedSequence([seed, world.rank]).generate_state(1)[0])


def average_gradients(model: torch.nn.Module, world: World) -> None:
    """Every trainable parameter's gradient averaged over the ranks, in one flat all-reduce (a parameter without a
    gradient on this rank counts as zero: all ranks must send the same tensors)."""
    if world.size <= 1:
        return
    params = [p for p in model.parameters() if p.requires_grad]
    for p in params:
        if p.grad is None:
            p.grad = torch.zeros_like(p)
    flat = torch.cat([p.grad.reshape(-1) for p in params])
    dist.all_reduce(flat)
    flat /= world.size
    offset = 0
    for p in params:
        n = p.numel()
        p.grad.copy_(flat[offset:offset + n].view_as(p))
        offset += n


def agree(flag: bool, world: World, device: torch.device | str = "cpu") -> bool:
    """Rank 0's `flag`, on every rank (`device`: the model's; NCCL sends CUDA tensors only)."""
    if world.size <= 1:
        return flag
    value = torch.tensor([1 if flag else 0], dtype=torch.int32, device=device)
    dist.broadcast(value, src=0)
    return bool(value.item())


def barrier(world: World) -> None:
    if world.size > 1:
        dist.barrier()


def shutdown(clean: bool = True) -> None:
    """Leave the process group before the process exits: every rank waits for the others (`clean`: the run ended
    without an error here), then the group is destroyed, as torch asks of every group. Left to the interpreter's
    exit, a gloo rank once aborted after its training had finished on a loaded machine ("terminate called without
    an active exception", SIGABRT: a C++ thread still running at teardown)."""
    if dist.is_available() and dist.is_initialized():
        if clean:
            dist.barrier()
        dist.destroy_process_group()
