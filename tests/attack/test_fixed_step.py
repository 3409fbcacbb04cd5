"""The fixed-shape detector part of the attack step: bit-identical to attack_loss eagerly; CUDA graph on a GPU."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from davis_rig.attack.eot import ClipPool, EoTConfig
from davis_rig.attack.fixed_step import FixedShapeAttackLoss
from davis_rig.attack.optimize import AttackConfig, attack_loss
from davis_rig.errors import ShapeError
from davis_rig.models.rvt.checkpoint import load_detector
from davis_rig.scene.body import BodyModel

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "rvt_mini_fixture.safetensors"
TINY_EOT = EoTConfig(supersample=1)
pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def detector():
    model = load_detector(FIXTURE).eval()
    for p in model.parameters():
        p.requires_grad_(False)
    return model


@pytest.fixture(scope="module")
def clips():
    return ClipPool(TINY_EOT, BodyModel(), 4, size=2, base_seed=5).sample(0, 2)


def _loss_and_grad(fn, grid_values):
    grid = grid_values.clone().requires_grad_(True)
    loss = fn(grid)
    loss.total.backward()
    return loss, grid.grad


@pytest.mark.parametrize("overrides", [{}, {"loss_reduction": "top"}, {"box_margin_px": 8.0},
                                       {"loss_anchors": "person"}, {"loss_anchors": "person", "loss_reduction": "top"}])
def test_eager_fixed_shape_loss_is_attack_loss_bit_for_bit(detector, clips, overrides):
    config = AttackConfig(grid_n=4, clips_per_step=2, eot=TINY_EOT, **overrides)
    grid = torch.rand(4, 4, generator=torch.Generator().manual_seed(1))
    want, want_grad = _loss_and_grad(lambda g: attack_loss(g, clips, detector, config), grid)
    fixed = FixedShapeAttackLoss(detector, config)
    for _ in range(2):  # the module is reused from step to step
        got, got_grad = _loss_and_grad(lambda g: fixed(g, clips), grid)
        for name in ("total", "obj", "cls", "num_anchors"):
            assert torch.equal(getattr(got, name), getattr(want, name)), name
        assert torch.equal(got_grad, want_grad) and got_grad.abs().sum() > 0


def test_modes_are_checked(detector):
    config = AttackConfig(grid_n=4, eot=TINY_EOT)
    with pytest.raises(ValueError, match="expected one of"):
        FixedShapeAttackLoss(detector, config, mode="jit")
    with pytest.raises(ValueError, match="records a CUDA graph: the detector is on cpu"):
        FixedShapeAttackLoss(detector, config, mode="cuda_graph")


@pytest.mark.gpu
def test_cuda_graph_replays_the_eager_loss_and_gradient(monkeypatch):
    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA device")
    # plain fp32 on both paths (cuDNN's default TF32 convolutions put the two 8.8e-4 apart on an H200). Even then two
    # eager runs differ: the backward's atomic adds sum in another order each time (on an H200, eager vs eager
    # 0.3-4.2e-5 of the gradient's norm, graph vs eager 0.3-8.3e-5; single cells up to 4e-4 where terms cancel), so
    # the gradient is compared by its norm
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", False)
    monkeypatch.setattr(torch.backends.cuda.matmul, "allow_tf32", False)
    cuda = torch.device("cuda")
    model = load_detector(FIXTURE).to(cuda).eval()
    for p in model.parameters():
        p.requires_grad_(False)
    config = AttackConfig(grid_n=4, clips_per_step=2, eot=TINY_EOT)
    moved = ClipPool(TINY_EOT, BodyModel(device=cuda), 4, size=2, base_seed=5).sample(0, 2)
    eager = FixedShapeAttackLoss(model, config)
    graphed = FixedShapeAttackLoss(model, config, mode="cuda_graph")
    for seed in range(3):  # replays with new texture values
        grid = torch.rand(4, 4, generator=torch.Generator().manual_seed(seed)).to(cuda)
        want, want_grad = _loss_and_grad(lambda g: eager(g, moved), grid)
        got, got_grad = _loss_and_grad(lambda g: graphed(g, moved), grid)
        torch.testing.assert_close(got.total, want.total, rtol=1e-5, atol=1e-6)
        assert float((got_grad - want_grad).norm() / want_grad.norm()) < 5e-4
    with pytest.raises(ShapeError, match="keep clips_per_step"):
        graphed(grid, moved[:1])
