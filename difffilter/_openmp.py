"""OpenMP's idle workers sleep instead of spinning, when difffilter is imported before torch.

A filter runs its time loop with one intra-op thread (:mod:`difffilter.threads`), but the code
around it (the caller's loss, the optimiser) runs at the caller's count, and every parallel region
it opens leaves torch's OpenMP workers busy-waiting for the next one (GNU OpenMP's default).  Those
spinning workers take the core the filter's single thread needs: measured on the 2-core machine with
one other process running, a KF training step (B = 256, T = 500, the benchmark's model) took 19-20
ms at torch's default two threads against 9-10 ms with ``OMP_WAIT_POLICY=PASSIVE`` or one thread.

The OpenMP runtime reads ``OMP_WAIT_POLICY`` once, when torch loads it, so this default can only be
set before ``import torch``: when ``torch`` is not imported yet and the variable is unset, it is set
to ``PASSIVE``.  A value the user set is kept; a process that imported torch first is unchanged
(export ``OMP_WAIT_POLICY=PASSIVE`` there).
"""

from __future__ import annotations

import os
import sys

__all__: list[str] = []

if "torch" not in sys.modules:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
