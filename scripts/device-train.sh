#!/usr/bin/env bash
# Context training on a lent GPU machine (the `device` tool), weights brought back. The project
# never depends on it; run it the moment a session's `status` says a device is lent.
#
# Here, once per session (builds the wgpu trainer, fetches the Vulkan loader, picks the start):
#   scripts/device-train.sh prepare [START.safetensors]   # default: the bundled model (with its context)
# Then one device call (carry the two folders; the command ends by itself at BUDGET seconds):
#   run(command="bash scripts/device-train.sh train 550", carry=[".device", ".gl"], timeout_s=600)
# (a first call finds the machine cold: about 30 s to start; 550 s leaves the 15 minutes room for
# one retry of a call that fails early; recording 10,000 oracle pairs took 200 s in session 23)
# Two runs share the GPU and one recording of the pairs (16 cores record 16 generator runs at
# once): both continue START's context on closed-loop pairs, A at batch 512 / lr 5e-4 and B at
# batch 128 / lr 2e-4 (session 23's run B, a fresh 4.6x larger context, got too few steps to say
# anything, and a wider context would not fit the step budget: session 29). At BUDGET both are
# stopped (their last checkpoints are whole: writes are atomic) and come back as
# $OUT/{a,b}.safetensors with their val.jsonl and logs. Export with
#   sgam train export FILES_AT/a.safetensors runs/a.safetensors
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
  # stripped it is about 100 MB, xz brings it to 31 (session 32; a call carries 64 MiB with the
  # tree, 27 MB of it)
  strip -o target-wgpu/sgam-stripped target-wgpu/release/sgam
  rm -f .device/sgam .device/base.safetensors
  xz -T0 -6 -c target-wgpu/sgam-stripped >.device/sgam.xz
  o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
  # NVIDIA's Vulkan driver (libGLX_nvidia) needs glvnd's libraries beside the loader: with
  # libvulkan1 alone the loader found no vkCreateInstance in it and wgpu no adapter (session 23)
  # shellcheck disable=SC2086
  apt-get $o update -qq && (cd .gl && apt-get $o download libvulkan1 libglvnd0 libegl1 libgl1 libglx0 \
    libopengl0 libgles2 >/dev/null)
  cp "${2:-models/compact.safetensors}" .device/start.safetensors
  du -sh .device .gl
  ;;
train)
  budget=${2:-540}
  t0=$(date +%s)
  for f in .gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
  if ! ls /usr/share/vulkan/icd.d/*.json >/dev/null 2>&1; then
    export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
  fi
  nvidia-smi -L || true
  # SGAM_BIN: another build for a dry run of this script (a CPU build here, small PAIRS and budget)
  bin=${SGAM_BIN:-/tmp/sgam}
  [ -n "${SGAM_BIN:-}" ] || { xz -T0 -dc .device/sgam.xz >/tmp/sgam && chmod +x /tmp/sgam; }
  rm -rf /tmp/ctxA /tmp/ctxB
  out=${OUT:-/tmp/out}
  mkdir -p "$out"
  # session 23 (batch 128): 156 pairs/s for A with B beside it, 1.2 steps/s, the GPU mostly waiting
  # on dispatches (burn-wgpu, many small kernels): a larger batch should cost little more a step
  # (not measured yet).
  # A and B continue START on the same closed-loop pairs (CL2's recipe: half the runs grow their
  # map with the model's own completions on 0.3 of their steps; recorded on the CPU kernels, 16
  # runs at once), with two recipes: A batch 512 at lr 5e-4, B batch 128 at lr 2e-4 (CL2's lr).
  # A new SEED records new pairs (its validation pairs change with it; step 0 is START's figure).
  common=(--pairs "${PAIRS:-6000}" --val-pairs "${VAL_PAIRS:-192}" --seed "${SEED:-12}" --closed-loop 0.5
    --closed-loop-steps 0.3 --warmup 20 --steps 1000000 --val-every 50 --ckpt-every 25 --time-limit 100000)
  "$bin" train context --run /tmp/ctxA --model .device/start.safetensors --batch "${BATCH_A:-512}" \
    --lr "${LR_A:-5e-4}" "${common[@]}" >"$out/a.log" 2>&1 &
  a=$!
  # B trains on A's pairs (--pairs-from) once A has written them: the same starting model and
  # options, so the same closed-loop pairs, read where they are
  b=
  alive() { kill -0 "$a" 2>/dev/null || { [ -n "$b" ] && kill -0 "$b" 2>/dev/null; }; }
  while alive && [ $(($(date +%s) - t0)) -lt $((budget - 20)) ]; do
    if [ -z "$b" ] && [ -f /tmp/ctxA/pairs-2.bin ]; then
      echo "pairs recorded after $(($(date +%s) - t0)) s"
      "$bin" train context --run /tmp/ctxB --model .device/start.safetensors --pairs-from /tmp/ctxA --batch "${BATCH_B:-128}" \
        --lr "${LR_B:-2e-4}" "${common[@]}" >"$out/b.log" 2>&1 &
      b=$!
    fi
    sleep 3
  done
  # (TERM: a non-interactive shell starts background jobs with SIGINT ignored)
  kill -TERM "$a" ${b:+"$b"} 2>/dev/null || true
  wait || true
  for r in a b; do
    d=/tmp/ctx${r^^}
    # f16, config embedded (a 256-wide context in f32 would pass the 16 MiB a file may bring back)
    [ -f $d/ckpt/model.safetensors ] && "$bin" train export $d/ckpt/model.safetensors "$out/$r.safetensors"
    [ -f $d/val.jsonl ] && cp $d/val.jsonl "$out/$r-val.jsonl"
    [ -f $d/log.jsonl ] && tail -n 400 $d/log.jsonl >"$out/$r-log.jsonl"
    echo "== $r"; grep -v '^\s*$' "$out/$r.log" 2>/dev/null | tail -n 12 || true
  done
  echo "done after $(($(date +%s) - t0)) s"
  ;;
*)
  echo "usage: $0 prepare [START.safetensors] | train [SECONDS]" >&2
  exit 2
  ;;
esac
