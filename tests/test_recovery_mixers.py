"""In-family parameter recovery for the Markov transition matrix (IMM) and the AR(1)
coefficient of coloured measurement noise: truth drawn from the filter's own model, training
by maximum likelihood from a perturbed start (small-scale CI versions)."""

from __future__ import annotations

import torch

from difffilter.filters import ColoredNoiseUKF, KalmanFilter
from difffilter.mixers import IMM
from difffilter.models import LinearModel

f64 = torch.float64


def _lbfgs(params, loss_fn, iters=40):
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=iters, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        return loss

    opt.step(closure)


def _rw_model(r: float) -> LinearModel:
    return LinearModel(
        F=torch.eye(1, dtype=f64), H=torch.eye(1, dtype=f64), Q=torch.full((1, 1), 0.05, dtype=f64), R=torch.full((1, 1), r, dtype=f64)
    )


def test_imm_recovers_transition_diagonal():
    true_pi = torch.tensor([[0.95, 0.05], [0.10, 0.90]], dtype=f64)
    r = torch.tensor([0.1, 9.0], dtype=f64)
    g = torch.Generator().manual_seed(0)
    B, T = 32, 300
    mode = torch.zeros(B, dtype=torch.long)
    x = torch.zeros(B, dtype=f64)
    zs = []
    for _ in range(T):
        mode = torch.multinomial(true_pi[mode], 1, generator=g)[:, 0]
        x = x + 0.05**0.5 * torch.randn(B, generator=g, dtype=f64)
        zs.append(x + r[mode].sqrt() * torch.randn(B, generator=g, dtype=f64))
    z = torch.stack(zs, 1)[..., None]
    start = torch.tensor([[0.7, 0.3], [0.3, 0.7]], dtype=f64)
    imm = IMM(
        [KalmanFilter(_rw_model(0.1)), KalmanFilter(_rw_model(9.0))], transition=start, initial_probs=torch.tensor([0.5, 0.5], dtype=f64)
    )
    params = [p for n, p in imm.named_parameters() if "transition" in n]
    assert params
    m0, P0 = torch.zeros(1, dtype=f64), torch.eye(1, dtype=f64)
    _lbfgs(params, lambda: -imm(z, m0, P0).log_likelihood.mean())
    learned = imm.transition.detach()
    print("learned transition", learned.tolist())
    assert (torch.diagonal(learned) - torch.diagonal(true_pi)).abs().max() < 0.05, learned


def test_colored_noise_ukf_recovers_psi_from_zero():
    psi_true, q, r = 0.7, 0.01, 1.0
    g = torch.Generator().manual_seed(1)
    B, T = 32, 200
    x = torch.zeros(B, dtype=f64)
    v = torch.randn(B, generator=g, dtype=f64) * (r / (1 - psi_true**2)) ** 0.5
    zs = []
    for _ in range(T):
        x = x + q**0.5 * torch.randn(B, generator=g, dtype=f64)
        v = psi_true * v + r**0.5 * torch.randn(B, generator=g, dtype=f64)
        zs.append(x + v)
    z = torch.stack(zs, 1)[..., None]
    model = LinearModel(
        F=torch.eye(1, dtype=f64), H=torch.eye(1, dtype=f64), Q=torch.full((1, 1), q, dtype=f64), R=torch.full((1, 1), r, dtype=f64)
    )
    flt = ColoredNoiseUKF(model, psi=torch.zeros(1, dtype=f64))
    model.requires_grad_(False)
    params = [p for n, p in flt.named_parameters() if "psi" in n]
    assert params
    m0, P0 = torch.zeros(1, dtype=f64), torch.eye(1, dtype=f64) * 2.0
    _lbfgs(params, lambda: -flt(z, m0, P0).log_likelihood.mean())
    print("learned psi", float(flt.psi.detach().reshape(-1)[0]))
    assert abs(float(flt.psi.detach().reshape(-1)[0]) - psi_true) < 0.05
