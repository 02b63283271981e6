"""Fast engines for the Kalman-family filters (see :class:`FusedFilter`).

* :mod:`.filter` - :class:`FusedFilter`, the front: validation, engine choice, fallback;
* generated engine: :mod:`.trace` (trace a filter's step), :mod:`.graph`, :mod:`.lower`,
  :mod:`.adjoint` (scalar graph, lowering of ATen operations, reverse mode), :mod:`.codegen`
  (C++ source), :mod:`.build` (compiler and on-disk cache), :mod:`.kernel` (autograd),
  :mod:`.generated` (batch packing);
* inductor engine: :mod:`.inductor` (the filter's own step under ``torch.compile``), :mod:`.step`
  (element-wise small linear algebra);
* both: :mod:`.branchfree` (branch-free stand-ins for the helpers that decide on data);
* :mod:`.policy`: which engine a plain filter call runs on (``DIFFFILTER_ENGINE``).
"""

from ..filters.base import ENGINE_HOOK
from .build import cache_dir
from .filter import ENGINES, FusedFilter, fuse
from .policy import chosen_engine, last_engine, run_compiled_if_chosen, set_engine

ENGINE_HOOK[0] = run_compiled_if_chosen

__all__ = ["ENGINES", "FusedFilter", "cache_dir", "chosen_engine", "fuse", "last_engine", "set_engine"]
