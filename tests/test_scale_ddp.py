"""Multi-process training and evaluation (``harness.distributed``) on CPU with the gloo backend, two processes.

The sharding functions are checked against hand-worked cases; two spawned processes train TinyDet with
DistributedDataParallel and predict held-out images (every image exactly once, gathered on rank 0); and
``torchrun -m harness run`` runs the whole job with rank 0 alone writing the store.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys

import pytest
import torch
from torch import nn

from harness.distributed import DistInfo, env_info, inference_shard, shard_order
from harness.engine.data import EpochSampler
from harness.errors import ConfigError


def test_inference_shards_partition_the_images_without_padding():
    assert [list(inference_shard(7, r, 2)) for r in range(2)] == [[0, 1, 2, 3], [4, 5, 6]]
    assert [list(inference_shard(5, r, 3)) for r in range(3)] == [[0, 1], [2, 3], [4]]
    assert [list(inference_shard(2, r, 4)) for r in range(4)] == [[0], [1], [], []]
    for n in range(0, 12):
        for world in range(1, 5):
            shards = [list(inference_shard(n, r, world)) for r in range(world)]
            assert sum(shards, []) == list(range(n))  # each image once, in order
            assert max(map(len, shards)) - min(map(len, shards)) <= 1
    with pytest.raises(ValueError):
        inference_shard(4, 2, 2)


def test_training_shards_cover_the_order_with_equal_lengths():
    order = [5, 3, 0, 4, 1, 2, 6]
    assert shard_order(order, 0, 2) == [5, 0, 1, 6]
    assert shard_order(order, 1, 2) == [3, 4, 2, 5]  # padded by wrapping around to the first index
    assert shard_order(order, 0, 1) == order
    s0, s1 = EpochSampler(7, seed=3, rank=0, world=2), EpochSampler(7, seed=3, rank=1, world=2)
    one = EpochSampler(7, seed=3)
    for epoch in (0, 1):
        for s in (s0, s1, one):
            s.set_epoch(epoch)
        assert len(s0) == len(s1) == 4 and len(list(s0)) == 4
        assert set(s0) | set(s1) == set(one) == set(range(7))
        # a global batch of 4 (2 per process) holds the same images as a single process's batch of 4
        assert sorted(list(s0)[:2] + list(s1)[:2]) == sorted(list(one)[:4])


def test_env_info_reads_the_torchrun_variables():
    assert env_info({}) == DistInfo(0, 1, 0) and not env_info({}).active
    d = env_info({"RANK": "1", "WORLD_SIZE": "2", "LOCAL_RANK": "1"})
    assert d.active and not d.is_main and d.local_rank == 1
    with pytest.raises(ConfigError, match="RANK=2 is not in 0..WORLD_SIZE-1"):
        env_info({"RANK": "2", "WORLD_SIZE": "2"})
    with pytest.raises(ConfigError, match="expected integers"):
        env_info({"RANK": "x", "WORLD_SIZE": "2"})


class OneBoxPerImage(nn.Module):
    """One detection per image, whose score encodes the process that predicted it."""

    conf, iou, max_det = 0.25, 0.7, 300

    def __init__(self, rank: int):
        super().__init__()
        self.w = nn.Parameter(torch.zeros(1))
        self.rank = rank

    def forward(self, x, targets=None):
        return [
            {
                "boxes": torch.tensor([[2.0, 2.0, 20.0, 20.0]]),
                "scores": torch.tensor([0.5 + 0.1 * self.rank]),
                "labels": torch.zeros(1, dtype=torch.long),
            }
            for _ in x
        ]


class WithUnused(nn.Module):
    """A detector plus a layer its forward never uses."""

    def __init__(self, inner: nn.Module):
        super().__init__()
        self.inner, self.spare = inner, nn.Linear(3, 3)

    def forward(self, x, targets=None):
        return self.inner(x, targets) if targets is not None else self.inner(x)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _worker(rank: int, world: int, port: int, folder: str, queue) -> None:
    os.environ.update(
        RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank), MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port)
    )
    torch.set_num_threads(1)
    from engine_helpers import ENCODINGS, tinydet_module, train_settings
    from harness import distributed as hd
    from harness.cache import PreparedDataset
    from harness.engine.data import AugmentSettings, SampleSource, TrainDataset
    from harness.engine.predict import predict
    from harness.engine.runtime import seed_everything
    from harness.engine.trainer import Trainer

    try:
        assert hd.init_from_env() == DistInfo(rank, world, rank)
        prepared = PreparedDataset(folder)
        train = SampleSource(prepared, list(range(8)), ENCODINGS[0])
        held_out = SampleSource(prepared, list(range(8, 15)), ENCODINGS[0])  # 7 images: shards of 4 and 3
        seed_everything(0)
        model = tinydet_module().build_tinydet(3, in_channels=4)
        settings = train_settings(epochs=2, batch=4, nominal_batch=4, seed=0)
        result = Trainer(model, TrainDataset(train, 64, AugmentSettings.off()), settings, progress=False).fit()
        flat = torch.cat([p.detach().flatten() for p in model.parameters()])
        weights = hd.gather_to_main(flat)
        # a detector with a parameter its forward never uses (as ICAFusion's layout has) still trains under DDP
        seed_everything(0)
        with_unused = WithUnused(tinydet_module().build_tinydet(3, in_channels=4))
        unused_result = Trainer(
            with_unused, TrainDataset(train, 64, AugmentSettings.off()), settings, progress=False
        ).fit()
        visited: list[int] = []
        dets = predict(OneBoxPerImage(rank), held_out, 64, batch=2, distributed=True, visited=visited)
        if rank == 0:
            queue.put(
                {
                    "epochs": result.epochs_run,
                    "unused_epochs": unused_result.epochs_run,
                    "same_weights": all(torch.equal(weights[0], w) for w in weights),
                    "dets": dets,
                    "visited": visited,
                    "expected": [held_out.image_id(k) for k in range(len(held_out))],
                }
            )
        else:
            queue.put({"rank1_dets": len(dets), "rank1_visited": len(visited)})
    except BaseException as exc:  # report instead of hanging the test
        queue.put({"error": f"rank {rank}: {type(exc).__name__}: {exc}"})
        raise
    finally:
        hd.shutdown()


@pytest.mark.slow
def test_two_gloo_processes_train_with_ddp_and_predict_each_image_once(tmp_path):
    import torch.multiprocessing as mp

    from engine_helpers import write_dataset

    write_dataset(tmp_path / "ds", groups=("A", "B"), per_group=8)
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    mp.start_processes(
        _worker, args=(2, _free_port(), str(tmp_path / "ds"), queue), nprocs=2, join=True, start_method="spawn"
    )
    out = {}
    for _ in range(2):
        out.update(queue.get(timeout=60))
    assert "error" not in out, out["error"]
    assert out["epochs"] == 2 and out["unused_epochs"] == 2
    assert out["same_weights"]  # DDP kept the two replicas identical
    assert len(out["dets"]) == len(out["expected"]) == 7  # one detection per image: each image predicted once
    assert [d["image_id"] for d in out["dets"]] == out["visited"] == out["expected"]
    assert sorted({round(d["score"], 2) for d in out["dets"]}) == [0.5, 0.6]  # both processes predicted
    assert out["rank1_dets"] == out["rank1_visited"] == 0  # gathered on rank 0 only


@pytest.mark.slow
def test_torchrun_harness_run_writes_the_store_from_rank_zero(tmp_path):
    from engine_helpers import set_args, shapes_run_args
    from scale_helpers import TINY, subprocess_env

    store = tmp_path / "store"
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc-per-node",
        "2",
        "--master-port",
        str(_free_port()),
        "-m",
        "harness",
        *shapes_run_args(store, *set_args([*TINY, "eval.batch=3"])),
    ]
    proc = subprocess.run(cmd, env=subprocess_env(tmp_path), capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert proc.stdout.count("tinydet on shapes") == 1  # rank 0 alone prints the tables
    run_dir = store / "shapes" / "tinydet" / "test-ir8" / "A" / "seed0"
    status = json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "finished" and status["world_size"] == 2
    m = json.loads((run_dir / "metrics.json").read_text())
    gt = json.loads((run_dir / "gt.json").read_text())
    assert m["train"]["processes"] == 2 and m["train"]["epochs_run"] == 2
    assert m["train"]["predict_images"] == m["support"]["images"] == len(gt["images"]) == 8
    gt_ids = {im["id"] for im in gt["images"]}
    assert {p["image_id"] for p in json.loads((run_dir / "predictions.json").read_text())} <= gt_ids
    log = [json.loads(line)["epoch"] for line in (run_dir / "log.jsonl").read_text().splitlines()]
    assert log == [1, 2]  # one record per epoch: only rank 0 logs
    assert {p.name for p in (run_dir / "checkpoints").iterdir()} == {"last.pt", "best.pt"}
