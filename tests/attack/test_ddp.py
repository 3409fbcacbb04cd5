"""DDP on CPU: 2 gloo processes, EoT samples split across ranks, averaged gradients == one process on the union."""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import torch

from davis_rig.attack.texture import TextureGenerator

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "rvt_mini_fixture.safetensors"
CONFIG_LR = 0.05  # the worker's AttackConfig.lr

WORKER = textwrap.dedent(
    """
    import os, sys
    import torch
    import torch.distributed as dist
    import torch.multiprocessing as mp

    from davis_rig.attack.eot import EoTConfig
    from davis_rig.attack.optimize import AttackConfig, optimize_texture
    from davis_rig.models.rvt.checkpoint import load_detector

    FIXTURE, OUT, PORT = sys.argv[1], sys.argv[2], sys.argv[3]
    CONFIG = AttackConfig(grid_n=4, iterations=2, clips_per_step=2, pool_size=2, refresh_every=1000,
                          num_validation_clips=1, validate_every=1000, checkpoint_every=1000, snapshot_every=1000,
                          lr=0.05, eot=EoTConfig(supersample=1))

    def run(rank, world):
        torch.set_num_threads(1)
        if world > 1:
            os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=PORT)
            dist.init_process_group("gloo", rank=rank, world_size=world)
        detector = load_detector(FIXTURE)
        optimize_texture(CONFIG, detector, os.path.join(OUT, f"world{world}"), progress=False)
        if world > 1:
            dist.destroy_process_group()

    if __name__ == "__main__":
        mp.spawn(run, args=(2,), nprocs=2, join=True)
        run(0, 1)
    """
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_gloo_ranks_equal_one_process_on_the_union(tmp_path):
    script = tmp_path / "worker.py"
    script.write_text(WORKER)
    proc = subprocess.run([sys.executable, str(script), str(FIXTURE), str(tmp_path), str(_free_port())],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    two = torch.load(tmp_path / "world2" / "checkpoints" / "last.pt", weights_only=True)
    one = torch.load(tmp_path / "world1" / "checkpoints" / "last.pt", weights_only=True)
    assert two["step"] == one["step"] == 2 and two["pool"] == one["pool"]
    torch.manual_seed(0)
    start = TextureGenerator(4).state_dict()
    for key, value in one["generator"].items():
        # ranks average per-rank means over 1 clip each; one process takes the mean over the batch of 2. The sums
        # run in another order, and Adam divides by sqrt(v): near-zero gradients turn rounding into update
        # differences of up to ~1e-3 lr (measured 3e-5 at lr 0.05), far below one step's size (lr).
        torch.testing.assert_close(two["generator"][key], value, rtol=1e-3, atol=2e-3 * CONFIG_LR)
    assert any(not torch.equal(one["generator"][k], start[k]) for k in start)  # the steps did move the weights
    logs = [[json.loads(x) for x in (tmp_path / f"world{w}" / "log.jsonl").read_text().splitlines()] for w in (1, 2)]
    assert len(logs[0]) == len(logs[1]) == 3  # 2 steps + the final validation
    for a, b in zip(logs[0][:2], logs[1][:2]):
        assert math.isclose(a["loss"], b["loss"], rel_tol=1e-5)  # logged loss = mean over all ranks' clips
