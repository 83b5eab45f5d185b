#!/usr/bin/env bash
# Installs what the Slurm campaign test needs (tools/experiments/tests/slurm.rs), idempotently:
# Debian's slurm-wlm (slurmctld, slurmd and the client commands) and munge. The test starts its
# own private single-node cluster (generated munge key and slurm.conf, own ports) and stops it by
# PID, so nothing here is configured or started. Without root or sudo it says SKIPPED and the
# test then skips loudly (it fails instead under CI=true).
set -euo pipefail

APT_PACKAGES=(slurm-wlm munge)
missing=()
for pkg in "${APT_PACKAGES[@]}"; do
  dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
done
((${#missing[@]})) || exit 0
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  if command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    SUDO="sudo"
  else
    echo "setup_slurm: SKIPPED installing ${missing[*]}: neither root nor passwordless sudo" >&2
    exit 0
  fi
fi
echo "setup_slurm: installing ${missing[*]}"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
