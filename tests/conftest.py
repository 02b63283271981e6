"""Test-session settings."""

import torch

# The filters work on many small tensors: intra-op threading only adds overhead (and contention
# on the 2-core CI machine), so tests run single-threaded.
torch.set_num_threads(1)
