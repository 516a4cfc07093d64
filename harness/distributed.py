"""Multi-process training under ``torchrun``: process group, data sharding, gathering, and "rank 0 writes".

``torchrun --nproc_per_node=N -m harness run ...`` starts N copies of the same command with ``RANK``,
``WORLD_SIZE`` and ``LOCAL_RANK`` in their environment. ``init_from_env()`` joins the process group (NCCL on GPUs,
gloo on CPUs) and every other piece of the harness asks this module what to do:

* training: each process takes every ``world``-th index of the epoch's shuffled order (``shard_order``), padded by
  wrapping around so that every process runs the same number of steps (DistributedDataParallel needs that);
* evaluation: ``inference_shard`` cuts the images into contiguous shards of unequal size, so that every image is
  predicted exactly once (PyTorch's ``DistributedSampler`` pads with repeated images, which would count some
  images twice), and ``gather_to_main`` collects the per-process results on rank 0 in the original order;
* only rank 0 writes the results store and checkpoints (``is_main``); the others wait at ``barrier`` where they
  read what rank 0 wrote.

Without ``torchrun`` (``WORLD_SIZE`` unset or 1) every function is a cheap no-op, so single-process code paths
are unchanged.
"""

from __future__ import annotations

import contextlib
import logging
import os
from dataclasses import dataclass
from datetime import timedelta
from typing import Any, Iterator, Sequence

from harness.errors import ConfigError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DistInfo:
    """This process's place in the job: ``rank`` of ``world_size`` processes, ``local_rank`` on its node."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def active(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def env_info(environ: Any = None) -> DistInfo:
    """The ``torchrun`` variables as a ``DistInfo``; malformed values are a clear error."""
    environ = os.environ if environ is None else environ
    try:
        world = int(environ.get("WORLD_SIZE", "1") or 1)
        rank = int(environ.get("RANK", "0") or 0)
        local = int(environ.get("LOCAL_RANK", str(rank)) or 0)
    except ValueError:
        raise ConfigError(
            f"RANK={environ.get('RANK')!r}, WORLD_SIZE={environ.get('WORLD_SIZE')!r}, "
            f"LOCAL_RANK={environ.get('LOCAL_RANK')!r}: expected integers (set by torchrun)"
        ) from None
    if world < 1 or not 0 <= rank < world:
        raise ConfigError(f"RANK={rank} is not in 0..WORLD_SIZE-1 (WORLD_SIZE={world})")
    return DistInfo(rank, world, local)


def _dist() -> Any:
    import torch.distributed as dist

    return dist if dist.is_available() else None


def is_initialized() -> bool:
    dist = _dist()
    return bool(dist is not None and dist.is_initialized())


def info() -> DistInfo:
    """The current process group's rank and size (``DistInfo()`` when there is none)."""
    if not is_initialized():
        return DistInfo()
    dist = _dist()
    return DistInfo(dist.get_rank(), dist.get_world_size(), env_info().local_rank)


def is_main() -> bool:
    return info().is_main


def init_from_env(backend: str | None = None, timeout_s: float = 1800.0) -> DistInfo:
    """Join the process group ``torchrun`` set up (once); nothing happens when ``WORLD_SIZE`` is 1 or unset.

    ``backend`` defaults to NCCL when CUDA is available, else gloo. On CUDA the process uses GPU ``LOCAL_RANK``.
    """
    env = env_info()
    if not env.active or is_initialized():
        return info() if is_initialized() else env
    import torch

    dist = _dist()
    if dist is None:
        raise ConfigError("WORLD_SIZE > 1 but this torch build has no torch.distributed support")
    if "MASTER_ADDR" not in os.environ or "MASTER_PORT" not in os.environ:
        raise ConfigError(
            "WORLD_SIZE > 1 but MASTER_ADDR / MASTER_PORT are not set; start the job with torchrun "
            "(see docs/scaling.md)"
        )
    cuda = torch.cuda.is_available()
    backend = backend or ("nccl" if cuda else "gloo")
    if cuda:
        torch.cuda.set_device(env.local_rank)
    dist.init_process_group(
        backend=backend,
        timeout=timedelta(seconds=timeout_s),
        **({"device_id": torch.device("cuda", env.local_rank)} if cuda and backend == "nccl" else {}),
    )
    log.info("process group %s: rank %d of %d (local rank %d)", backend, env.rank, env.world_size, env.local_rank)
    return info()


def shutdown() -> None:
    if is_initialized():
        _dist().destroy_process_group()


def barrier() -> None:
    if info().active:
        dist = _dist()
        if dist.get_backend() == "nccl":
            import torch

            dist.barrier(device_ids=[torch.cuda.current_device()])
        else:
            dist.barrier()


@contextlib.contextmanager
def main_first() -> Iterator[None]:
    """Rank 0 runs the block first (e.g. preparing a dataset cache), then the others (which then read the cache)."""
    d = info()
    if d.active and not d.is_main:
        barrier()
    yield
    if d.active and d.is_main:
        barrier()


def broadcast_object(obj: Any, src: int = 0) -> Any:
    """Rank ``src``'s ``obj`` on every process (picklable objects)."""
    if not info().active:
        return obj
    box = [obj]
    _dist().broadcast_object_list(box, src=src, device=_object_device())
    return box[0]


def gather_to_main(obj: Any) -> list[Any] | None:
    """Every process's ``obj`` as a list in rank order on rank 0; ``None`` on the other ranks."""
    d = info()
    if not d.active:
        return [obj]
    out: list[Any] | None = [None] * d.world_size if d.is_main else None
    dist = _dist()
    if dist.get_backend() == "nccl":  # gather_object on NCCL needs the current device; all_gather is simpler
        everyone: list[Any] = [None] * d.world_size
        dist.all_gather_object(everyone, obj)
        return everyone if d.is_main else None
    dist.gather_object(obj, out, dst=0)
    return out


def any_process(flag: bool) -> bool:
    """True on every process when ``flag`` is true on at least one of them."""
    if not info().active:
        return bool(flag)
    import torch

    t = torch.tensor([1 if flag else 0], dtype=torch.int64, device=_object_device() or "cpu")
    _dist().all_reduce(t, op=_dist().ReduceOp.MAX)
    return bool(t.item())


def all_reduce_mean(values: dict[str, float]) -> dict[str, float]:
    """Mean over the processes of a dict of floats (same keys everywhere), e.g. the epoch's mean losses."""
    d = info()
    if not d.active or not values:
        return values
    import torch

    keys = sorted(values)
    t = torch.tensor([float(values[k]) for k in keys], dtype=torch.float64, device=_object_device() or "cpu")
    _dist().all_reduce(t)
    return {k: float(v) / d.world_size for k, v in zip(keys, t.tolist())}


def _object_device() -> Any:
    import torch

    if _dist().get_backend() == "nccl":
        return torch.device("cuda", torch.cuda.current_device())
    return None


# ------------------------------------------------------------------------------------------------- sharding
def inference_shard(n: int, rank: int, world: int) -> range:
    """Contiguous shard ``rank`` of ``range(n)`` cut into ``world`` pieces whose sizes differ by at most one.

    The shards partition ``range(n)`` exactly: no index is repeated (no padding) and none is left out, so the
    concatenation of the shards in rank order is ``range(n)``. A shard may be empty when ``n < world``.
    """
    if world < 1 or not 0 <= rank < world:
        raise ValueError(f"rank {rank} of world size {world}")
    size, extra = divmod(int(n), int(world))
    start = rank * size + min(rank, extra)
    return range(start, start + size + (1 if rank < extra else 0))


def shard_order(order: Sequence[int], rank: int, world: int) -> list[int]:
    """Process ``rank``'s part of an epoch order for training: every ``world``-th index, after padding the order by
    wrapping around to a multiple of ``world`` so that every process runs the same number of iterations."""
    order = list(order)
    if world <= 1 or not order:
        return order
    total = -(-len(order) // world) * world
    padded = (order * (total // len(order) + 1))[:total]
    return padded[rank::world]
