#!/usr/bin/env bash
# Issue 29's GPU checks in one call (budget: about 8 min on an H100), from the repository root:
#   here, once:   bash experiments/gpu_wheels.sh            (dynamax + dependencies into .whl/)
#   device tool:  run(command="bash experiments/gpu_check.sh", carry=[".whl"], timeout_s=600)
# 1. the CUDA tests (tests/test_parallel_cuda.py, test_parallel_filter.py::test_cuda_equals_cpu);
# 2. experiments/benchmark_parallel.py on cuda at T = 1e4, B = 1 and 64: the sequential filter
#    (default path = eager off the CPU), the parallel filter, dynamax's parallel filter on the same GPU;
# 3. experiments/benchmark_gpu_ukf.py: the benchmark's UKF training step at B = 4096 (eager and
#    FusedFilter(inductor) on the GPU, the CPU default path, dynamax's UKF).
# Outputs land in $OUT (the device tool's folder; /tmp/gpu_check elsewhere). Without dynamax the peer
# columns are skipped and the reason printed; each step has its own timeout so one cannot eat the rest.
set -u
OUT=${OUT:-/tmp/gpu_check}
mkdir -p "$OUT"
PY=${PYTHON:-python3}
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
# JAX would otherwise take 75 % of the GPU memory at its first call, next to torch in the same process
export XLA_PYTHON_CLIENT_PREALLOCATE=false
if ls .whl/*.whl >/dev/null 2>&1; then
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && export PYTHONPATH="$PYTHONPATH:/tmp/site"
fi
{
  date -u; nvidia-smi -L 2>&1
  $PY -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), torch.cuda.get_device_name() if torch.cuda.is_available() else '-')"
} 2>&1 | tee "$OUT/env.log"
PEER=""
if ! $PY -c "import jax; from dynamax.linear_gaussian_ssm import parallel_inference; print('jax', jax.__version__, jax.devices())" 2>&1 | tee -a "$OUT/env.log"; then
  PEER="--no-peer"; echo "dynamax not importable: peer columns skipped (run experiments/gpu_wheels.sh here and carry .whl)" | tee -a "$OUT/env.log"
fi
status=0
timeout 200 $PY -m pytest -q -rs -p no:cacheprovider tests/test_parallel_cuda.py tests/test_parallel_filter.py::test_cuda_equals_cpu 2>&1 | tee "$OUT/tests.log"
[ "${PIPESTATUS[0]}" -eq 0 ] || status=1
if ! $PY -c "import torch, sys; sys.exit(not torch.cuda.is_available())"; then
  echo "no CUDA device: the CUDA tests skipped themselves; GPU benchmarks skipped" | tee -a "$OUT/env.log"
  exit $status
fi
timeout 180 $PY experiments/benchmark_parallel.py --device cuda --steps 10000 --batches 1 64 --max-elements 1000000 \
  --max-sequential 1000000 --repeats 1 $PEER --out "$OUT/benchmark_parallel_gpu.md" 2>&1 | tee "$OUT/benchmark_parallel.log"
[ "${PIPESTATUS[0]}" -eq 0 ] || status=1
timeout 180 $PY experiments/benchmark_gpu_ukf.py --batch 4096 --steps 500 --repeats 2 $PEER --out "$OUT/gpu_ukf.md" 2>&1 | tee "$OUT/gpu_ukf.log"
[ "${PIPESTATUS[0]}" -eq 0 ] || status=1
date -u
exit $status
