#!/usr/bin/env bash
# Install the peer engines used only by `python -m benchmarks` (never runtime dependencies).
# Each is optional: the benchmark skips a peer that is missing and says so in REPORT.md.
set -u
pip install mujoco || echo "MuJoCo could not be installed: skipped"
# --no-deps: the benchmarks drive its compiled binding (compas_lmgc90._lmgc90) directly, so
# nothing of COMPAS (which its Solver module imports) is needed
pip install --no-deps compas-lmgc90 || echo "compas-lmgc90 (LMGC90) could not be installed: skipped"
if command -v apt-get >/dev/null; then
  if [ "$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi
  $SUDO apt-get update -qq && \
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y --no-install-recommends yade \
    || echo "YADE (Debian package yade) could not be installed: skipped"
else
  echo "no apt-get: YADE skipped"
fi
