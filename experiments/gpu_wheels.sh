#!/usr/bin/env bash
# Download (here, where pip reaches the registry) the wheels that experiments/gpu_check.sh needs on
# the GPU machine, whose image lacks dynamax and its dependencies (nothing can be fetched there).
# Writes .whl/ (git-ignored through .git/info/exclude) in the repository root; about 7.5 MB.
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
grep -qx '/.whl/' "$(git rev-parse --git-common-dir)/info/exclude" 2>/dev/null || echo '/.whl/' >>"$(git rev-parse --git-common-dir)/info/exclude"
# the versions installed on the CPU machine, where the dynamax peer ran (python 3.12 on the GPU image)
python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
  dynamax==1.0.3 tfp-nightly==0.26.0.dev20261027 fastprogress==1.1.6 decorator==5.2.1 dm-tree==0.1.10 gast==0.7.0
ls -la .whl
