#!/usr/bin/env bash
# Install the Debian packages the tests need, once. Nothing to do when they are already present.
set -euo pipefail
needed=()
for pkg in "$@"; do
  dpkg -s "$pkg" >/dev/null 2>&1 || needed+=("$pkg")
done
if [ ${#needed[@]} -eq 0 ]; then
  exit 0
fi
if [ "$(id -u)" -ne 0 ]; then
  echo "system-deps: need root to install: ${needed[*]}; run: sudo make system-deps (or sudo apt-get install -y ${needed[*]})" >&2
  exit 1
fi
echo "system-deps: installing ${needed[*]}"
apt-get update -qq
DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${needed[@]}" >/dev/null
