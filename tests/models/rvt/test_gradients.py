"""Input gradients: the official 3-step BPTT gradient of the RVT-T fixture, and a float64 finite-difference check."""

from __future__ import annotations

import copy

import torch

from davis_rig.models.rvt import load_detector
from davis_rig.models.rvt.detector import pad_to_input

# Measured on the dev machine (AMD EPYC, AVX2, 2 threads): loss 162.88078 vs 162.88081 (rel 2e-7);
# max |grad - ref| / max |ref| = 1.06e-5, 8.8e-6, 8.1e-6 for the inputs of steps 0, 1, 2.
RTOL_LOSS = 1e-5
RTOL_GRAD = 1e-4  # relative to the largest gradient magnitude of each input


def _loss(decoded: torch.Tensor) -> torch.Tensor:
    """The fixture's loss: Σ_anchors obj · max_c cls_c of the decoded output."""
    return (decoded[..., 4] * decoded[..., 5:].max(dim=-1).values).sum()


def _bptt_input_grads(model, hist_uint8: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
    for parameter in model.parameters():
        parameter.requires_grad_(False)
    inputs = [pad_to_input(hist_uint8[t : t + 1]).to(next(model.parameters()).dtype).requires_grad_(True)
              for t in range(hist_uint8.shape[0])]
    states = None
    for x in inputs:
        decoded, states = model(x, states)
    loss = _loss(decoded)
    loss.backward()
    return loss.detach(), [x.grad for x in inputs]


def test_rvt_t_bptt_input_gradients_match_official(rvt_t_fixture, rvt_t_grad_fixture):
    model = load_detector(rvt_t_fixture.path)
    loss, grads = _bptt_input_grads(model, rvt_t_fixture.tensor("input.hist_uint8_unpadded"))
    ref_loss = float(rvt_t_grad_fixture["grad.loss"][0])
    assert abs(float(loss) - ref_loss) <= RTOL_LOSS * abs(ref_loss), (float(loss), ref_loss)
    for step, grad in enumerate(grads):
        ref = rvt_t_grad_fixture.tensor(f"grad.step{step}.input_padded")
        assert grad.shape == ref.shape == (1, 20, 256, 320)
        rel = float((grad - ref).abs().max() / ref.abs().max())
        assert rel <= RTOL_GRAD, f"step {step}: max |grad - ref| / max |ref| = {rel:.2e}"
        cosine = torch.nn.functional.cosine_similarity(grad.double().flatten(), ref.double().flatten(), dim=0)
        assert float(cosine) > 1 - 1e-8


def test_mini_gradient_matches_finite_differences_float64(mini_fixture):
    """Directional derivative of the 3-step loss w.r.t. all inputs: autograd vs central differences, float64."""
    model = copy.deepcopy(load_detector(mini_fixture.path)).double()
    hist = mini_fixture.tensor("input.hist_uint8_unpadded")
    loss, grads = _bptt_input_grads(model, hist)
    assert all(float(g.abs().max()) > 0 for g in grads)  # the gradient reaches every step through the LSTM states

    generator = torch.Generator().manual_seed(0)
    directions = [torch.randn(g.shape, generator=generator, dtype=torch.float64) for g in grads]
    analytic = sum(float((g * d).sum()) for g, d in zip(grads, directions))

    def loss_at(eps: float) -> float:
        with torch.no_grad():
            states = None
            for t, d in enumerate(directions):
                x = pad_to_input(hist[t : t + 1]).double() + eps * d
                decoded, states = model(x, states)
            return float(_loss(decoded))

    eps = 1e-7  # the random-weight model is strongly curved: larger steps measure curvature, not the slope
    numeric = (loss_at(eps) - loss_at(-eps)) / (2 * eps)
    assert abs(numeric - analytic) <= 1e-5 * max(1.0, abs(analytic)), (numeric, analytic)
