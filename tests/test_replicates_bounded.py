"""Seeded start perturbation of bounded parameters (learn/replicates.py): a step in logit space.

References are computed independently of the implementation: the draws from the documented
generator contract (one float64 ``torch.randn`` per value shape, sorted names, seeded with
``seed``) and logits with numpy in float64.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf
from torch import nn

import difffilter.learn  # noqa: F401  (registers the replicate_seed resolver)
from difffilter.learn.replicates import perturb_initial_values
from difffilter.params import Bounded, Interval, register_constrained
from difffilter.selection import assign_parameters, parameter_owners, select_parameters
from experiments.papers.smartloc import SharedPsiColoredUKF

CONF = Path(__file__).resolve().parents[1] / "conf"


class _Bounded(nn.Module):
    """Psi [7] in (-1, 1) at p001's 0.7, rho in (0, 1) at p002's 0.95, an exponent in (-4, 4) at 0,
    a linear Interval in [2, 6] and a log-scale Interval in [1, 1e3]."""

    def __init__(self, dtype: torch.dtype) -> None:
        super().__init__()
        register_constrained(self, "psi", torch.full((7,), 0.7, dtype=dtype), Bounded(-1.0, 1.0))
        register_constrained(self, "rho", torch.tensor(0.95, dtype=dtype), Bounded(0.0, 1.0))
        register_constrained(self, "exponent", torch.tensor(0.0, dtype=dtype), Bounded(-4.0, 4.0))
        register_constrained(self, "lin", torch.tensor([2.5, 5.9], dtype=dtype), Interval(2.0, 6.0, log_scale=False))
        register_constrained(self, "tau", torch.tensor([10.0, 100.0], dtype=dtype), Interval(1.0, 1e3))


_BOUNDS = {"psi": (-1.0, 1.0), "rho": (0.0, 1.0), "exponent": (-4.0, 4.0), "lin": (2.0, 6.0)}


def _draws(module: nn.Module, names: list[str], seed: int) -> dict[str, np.ndarray]:
    gen = torch.Generator().manual_seed(seed)
    owners = parameter_owners(module)
    return {n: torch.randn(getattr(owners[n][0], owners[n][1]).shape, generator=gen, dtype=torch.float64).numpy() for n in sorted(names)}


def _logit(v: np.ndarray, lo: float, hi: float) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return np.log(v - lo) - np.log(hi - v)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("sigma", [0.2, 3.0])
def test_bounded_starts_move_by_sigma_z_in_logit_space_and_stay_inside(dtype, sigma):
    mod = _Bounded(dtype)
    names = select_parameters(mod, list(_BOUNDS))
    before = {n: getattr(mod, n).detach().double().numpy().copy() for n in _BOUNDS}
    z = _draws(mod, names, seed=3)
    new = perturb_initial_values(mod, names, sigma, seed=3)
    eps = float(torch.finfo(dtype).eps)
    for name, (lo, hi) in _BOUNDS.items():
        after = getattr(mod, name).detach().double().numpy()
        assert new[name].dtype == dtype
        assert np.all(after > lo) and np.all(after < hi), (name, after)
        moved = _logit(after, lo, hi) - _logit(before[name], lo, hi)
        f = (after - lo) / (hi - lo)
        # the stored value is rounded to the dtype: its logit is known to eps |v| / (w f (1 - f)), twice for the start
        tol = 4 * eps * np.maximum(np.abs(after), 1.0) / ((hi - lo) * f * (1 - f)) + 1e-9
        np.testing.assert_array_less(np.abs(moved - sigma * z[name]), tol)
        np.testing.assert_allclose(np.abs(moved), sigma * np.abs(z[name]), atol=float(np.max(tol)))


def test_sigma_zero_changes_nothing_and_each_seed_reproduces():
    mod = _Bounded(torch.float64)
    names = select_parameters(mod, list(_BOUNDS) + ["tau"])
    before = {n: getattr(mod, n).detach().clone() for n in list(_BOUNDS) + ["tau"]}
    assert perturb_initial_values(mod, names, 0.0, seed=5) == {}
    for n, v in before.items():
        assert torch.equal(getattr(mod, n), v)
    a, b, c = _Bounded(torch.float64), _Bounded(torch.float64), _Bounded(torch.float64)
    ra = perturb_initial_values(a, names, 0.2, seed=5)
    rb = perturb_initial_values(b, names, 0.2, seed=5)
    rc = perturb_initial_values(c, names, 0.2, seed=6)
    for n in ra:
        assert torch.equal(ra[n], rb[n])
    assert not torch.equal(ra["psi"], rc["psi"]) and not torch.equal(ra["rho"], rc["rho"])


def test_log_scale_interval_keeps_the_multiplicative_step_and_folds_at_its_bounds():
    """A log-scale Interval keeps value exp(sigma z) inside (the committed p000 / smartloc starts) and
    mirrors log value at the bound instead of clamping next to it; no warning either way."""
    small, big = _Bounded(torch.float64), _Bounded(torch.float64)
    names = select_parameters(small, ["tau"])
    z = _draws(small, names, seed=0)["tau"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        perturb_initial_values(small, names, 0.01, seed=0)
        perturb_initial_values(big, names, 50.0, seed=0)
    # inside the bounds: the multiplicative step bit for bit (the committed p000 / smartloc starts are unchanged)
    old_rule = _Bounded(torch.float64)
    assign_parameters(old_rule, {"tau": old_rule.tau.detach() * torch.exp(0.01 * torch.from_numpy(z))})
    assert torch.equal(small.tau.detach(), old_rule.tau.detach())
    # independent fold: y = log v + 50 z reflected into [0, log 1e3]
    length = math.log(1e3)
    t = np.mod(np.log([10.0, 100.0]) + 50.0 * z, 2 * length)
    expected = np.exp(np.where(t <= length, t, 2 * length - t))
    np.testing.assert_allclose(big.tau.detach().numpy(), expected, rtol=1e-12)
    assert np.all(big.tau.detach().numpy() > 1.0) and np.all(big.tau.detach().numpy() < 1e3)


def test_a_start_on_a_bound_stays_on_it():
    """rho = 1 (no fading) is held at the nearest value inside; the logit step leaves it there."""
    for dtype in (torch.float32, torch.float64):
        mod = nn.Module()
        register_constrained(mod, "rho", torch.tensor(1.0, dtype=dtype), Bounded(0.0, 1.0))
        start = mod.rho.detach().clone()
        perturb_initial_values(mod, ["rho"], 0.5, seed=1)
        rho = float(mod.rho.detach())
        assert rho < 1.0 and abs(rho - float(start)) <= 2 * float(torch.finfo(dtype).eps)


def test_a_shared_bounded_value_moves_as_one():
    filt = SharedPsiColoredUKF(_p001_model(), psi=0.7)
    z0 = _draws(filt, ["psi"], seed=2)["psi"].reshape(-1)[0]
    perturb_initial_values(filt, ["psi"], 0.2, seed=2)
    psi = filt.psi.detach().numpy()
    assert np.all(psi == psi[0])
    np.testing.assert_allclose(_logit(psi[0], -1.0, 1.0) - _logit(0.7, -1.0, 1.0), 0.2 * z0, atol=1e-12)


def _p001_model() -> nn.Module:
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=["experiment=p001_multipath"])
    return instantiate(cfg.model, _convert_="all")


@pytest.mark.parametrize("seed", [2, 3])
def test_p001_multipath_seeds_2_and_3_now_start_at_reachable_logits(seed):
    """p001's per-channel seeds 2 and 3 pushed one channel's Psi past 1 (0.7 exp(0.2 z) = 1.07, 1.18),
    clamped to logit 13.8; now every channel starts within 0.2 |z| logit units of logit(0.7) = 1.73."""
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=["experiment=p001_multipath", f"seed={seed}"])
    filt = instantiate(cfg.filter, _convert_="all")
    assign_parameters(filt, OmegaConf.to_container(cfg.experiment.hand_tuned, resolve=True))
    names = select_parameters(filt, list(cfg.learn))
    z = _draws(filt, names, seed)["psi"]
    assert np.any(0.7 * np.exp(0.2 * z) > 1.0)  # the old multiplicative start passed the bound for this seed
    perturb_initial_values(filt, names, float(cfg.learner.init_perturbation), seed=int(cfg.learner.init_seed))
    psi = filt.psi.detach().numpy()
    u = _logit(psi, -1.0, 1.0)
    np.testing.assert_allclose(u - _logit(0.7, -1.0, 1.0), 0.2 * z, atol=1e-12)
    assert np.all(np.isfinite(u)) and float(np.max(np.abs(u))) < 3.0  # logit 13.8 before; Adam (lr 0.1) moves ~0.1 per step
