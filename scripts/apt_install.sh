#!/usr/bin/env bash
# Installs the Debian packages named that are not installed yet (idempotent; sudo when not
# root). Usage: scripts/apt_install.sh WHO PACKAGE...   (WHO prefixes the one line it prints)
set -euo pipefail
who="$1"
shift
missing=()
for pkg in "$@"; do
  dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
done
if ((${#missing[@]})); then
  echo "$who: installing ${missing[*]}"
  SUDO=""
  [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
fi
