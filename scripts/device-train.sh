#!/usr/bin/env bash
# Ten minutes of context training on a lent GPU machine (the `device` tool), weights brought back.
# The project never depends on it; run it the moment a session's `status` says a device is lent.
#
# Here, once per session (builds the wgpu trainer, fetches the Vulkan loader, picks the start):
#   scripts/device-train.sh prepare [START.safetensors]   # default: the run's or the bundled model
# Then one device call (carry the two folders; 600 s leaves room for the machine's start):
#   run(command="bash scripts/device-train.sh train 420", carry=[".device", ".gl"], timeout_s=600)
# The weights come back as $OUT/model.safetensors (files_at); export them with
#   sgam train export FILES_AT/model.safetensors models/compact.safetensors
# and judge them with `sgam eval world` before bundling.
set -euo pipefail
cd "$(dirname "$0")/.."
case "${1:-}" in
prepare)
  grep -qxF '/.device/' .git/info/exclude || echo '/.device/' >>.git/info/exclude
  grep -qxF '/.gl/' .git/info/exclude || echo '/.gl/' >>.git/info/exclude
  mkdir -p .device .gl /tmp/amd64/partial
  # burn's wgpu backend builds offline (its cuda backend would download LLVM); no debuginfo, so
  # the binary fits a transfer
  CARGO_PROFILE_RELEASE_DEBUG=false cargo build --release -p sgam --features sgam-model/wgpu --target-dir target-wgpu
  strip -o .device/sgam target-wgpu/release/sgam
  o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
  # shellcheck disable=SC2086
  apt-get $o update -qq && (cd .gl && apt-get $o download libvulkan1 >/dev/null)
  cp "${2:-models/compact.safetensors}" .device/start.safetensors
  du -sh .device .gl
  ;;
train)
  seconds=${2:-420}
  for f in .gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
  if ! ls /usr/share/vulkan/icd.d/*.json >/dev/null 2>&1; then
    export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
  fi
  out=${OUT:-/tmp/out}
  mkdir -p "$out"
  # 16 cores record the pairs in about 2 minutes; the GPU trains for the rest
  ./.device/sgam train context --run /tmp/ctx --model .device/start.safetensors --pairs 6000 \
    --val-pairs 192 --batch 64 --lr 5e-4 --steps 100000 --val-every 200 --ckpt-every 100 \
    --time-limit "$seconds" 2>&1 | tail -40
  cp /tmp/ctx/ckpt/model.safetensors /tmp/ctx/val.jsonl "$out"/
  ;;
*)
  echo "usage: $0 prepare [START.safetensors] | train [SECONDS]" >&2
  exit 2
  ;;
esac
