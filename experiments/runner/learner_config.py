"""The ``learner`` config node mapped onto the library's objects.

The config keeps its flat keys (``learner.dtype``, ``learner.fused``, ``learner.smoother``,
``learner.init_perturbation``...) while :class:`~difffilter.learn.learner.FilterLearner` takes
few arguments.  :func:`split_learner_config` sorts the keys:

* :class:`~difffilter.learn.learner.LearnerOptions` fields become its ``options`` (a config
  with a ``_target_``, so that Hydra builds the object);
* ``log_prior`` and ``prior_weight`` become its ``prior``
  (:class:`~difffilter.learn.losses.LogPrior`);
* ``dtype``, ``fused``, ``init_perturbation``, ``init_seed`` and ``figure_every_n_epochs`` are
  the runner's: :func:`finish_learner` converts the filter, perturbs the learned start values
  and sets the compiled engine; the figures are a :class:`~difffilter.learn.plots.DiagnosticFigures`
  callback (:func:`figure_callback`);
* every other key (``learn``, ``optimizer``, ``scheduler``, a paper factory's own keywords such
  as ``start_params``) goes to the ``_target_`` as it is.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from difffilter._util import as_dtype
from difffilter.engines import FusedFilter
from difffilter.learn.learner import FilterLearner, LearnerOptions
from difffilter.learn.losses import LogPrior
from difffilter.learn.plots import DiagnosticFigures
from difffilter.learn.replicates import perturb_initial_values

__all__ = ["RUNNER_KEYS", "figure_callback", "finish_learner", "split_learner_config"]

#: learner.* keys the runner applies itself (not arguments of the learner)
RUNNER_KEYS = ("dtype", "fused", "init_perturbation", "init_seed", "figure_every_n_epochs")
_OPTION_KEYS = tuple(f.name for f in dataclasses.fields(LearnerOptions))
_OPTIONS_TARGET = f"{LearnerOptions.__module__}.{LearnerOptions.__qualname__}"
_PRIOR_TARGET = f"{LogPrior.__module__}.{LogPrior.__qualname__}"


def split_learner_config(learner: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(the config of the learner factory, the runner's settings)`` from a plain ``learner``
    config (see the module docstring)."""
    cfg = dict(learner)
    runner = {k: cfg.pop(k) for k in RUNNER_KEYS if k in cfg}
    options = {k: cfg.pop(k) for k in _OPTION_KEYS if k in cfg}
    log_prior, weight = cfg.pop("log_prior", None), cfg.pop("prior_weight", 1.0)
    if fused := runner.get("fused", False):
        if fused not in (True, "eager"):
            raise ValueError(f"learner.fused must be false, true or 'eager', got {fused!r}")
    if options:
        cfg["options"] = {"_target_": _OPTIONS_TARGET, **options}
    if log_prior:
        cfg["prior"] = {"_target_": _PRIOR_TARGET, "priors": log_prior, "weight": weight}
    return cfg, runner


def finish_learner(learner: FilterLearner, settings: Mapping[str, Any]) -> FilterLearner:
    """Apply the runner's ``settings`` (from :func:`split_learner_config`) to a new learner, in
    the order the learner once applied them itself: the filter converted to ``dtype``, the
    learned start values perturbed (``init_perturbation``, seeded by ``init_seed``), then the
    compiled engine (``fused``: ``True`` the default engine, ``"eager"`` uncompiled)."""
    if settings.get("dtype") is not None:
        learner.filter.to(as_dtype(settings["dtype"]))
        learner.set_options(learner.options)  # the initial-belief buffers follow the filter's dtype
    sigma = float(settings.get("init_perturbation") or 0.0)
    perturb_initial_values(learner.filter, learner.learned_names, sigma, seed=int(settings.get("init_seed") or 0))
    fused = settings.get("fused", False)
    if fused:
        learner.set_engine(FusedFilter(learner.filter, compile=fused is True))  # type: ignore[arg-type]
    return learner


def figure_callback(learner: Mapping[str, Any] | None) -> DiagnosticFigures:
    """The figures callback of a ``learner`` config (``figure_every_n_epochs``, default 1)."""
    every = (learner or {}).get("figure_every_n_epochs")
    return DiagnosticFigures(every_n_epochs=1 if every is None else int(every))
