"""README's example learns the pendulum's noise as written, and its test command is the one CI runs."""

from __future__ import annotations

import re

import torch

from difffilter.filters import UKF

from .readme_snippets import ROOT, page_namespace, readme_snippets

HEADING = "## Learn the noise of your own model"


def test_readme_example_learns_the_noise() -> None:
    assert len(readme_snippets(HEADING)) == 1
    ns = page_namespace("README.md")
    model, truth, data = ns["model"], ns["truth"], ns["data"]
    Q, R = model.Q.detach(), model.R.detach()
    # the starting guess was 10x off in every variance; the learned ones land near the truth's
    assert 0.7 < float(R[0, 0]) / 0.01 < 1.4
    assert 0.6 < float(Q[1, 1]) / 4e-3 < 1.6
    assert float(Q[0, 0]) < 1e-3  # the small angle noise is barely identified, but far below the start's 1e-2
    with torch.no_grad():
        learned = -UKF(model)(data.measurements, data.initial_mean, data.initial_cov).log_likelihood.mean()
        oracle = -UKF(truth)(data.measurements, data.initial_mean, data.initial_cov).log_likelihood.mean()
    assert float(learned) < float(oracle) + 0.01  # the likelihood of the truth's parameters, or better


def test_readme_is_short_and_links_exist() -> None:
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 150
    for target in re.findall(r"\]\(([^)#]+)\)", text):
        if not target.startswith("http"):
            assert (ROOT / target).exists(), target


def test_ci_runs_the_readme_test_command() -> None:
    readme = (ROOT / "README.md").read_text()
    ci = (ROOT / ".ci" / "run").read_text()
    command = "python -m pytest -q"
    assert f"&& {command}\n" in readme
    assert f"\n{command}\n" in ci
    # the slow suite runs as its own step, after the default suite
    slow = f"\n{command} -m slow\n"
    assert slow in ci and ci.index(slow) > ci.index(f"\n{command}\n")
