#!/usr/bin/env bash
# The model's compute rate against this machine's best f32 GEMM, side by side in one run:
# numpy's 1024x1024 matrix product (OpenBLAS), then `sgam bench refine` (the model's GFLOP per
# refine, its achieved GFLOP/s and burn's own 1024x1024 GEMM). Installs numpy with pip when it
# is missing (the peer is the benchmark's, never the tests').
# Usage: bench/gemm_peer.sh [--model FILE] [--res 256]   (extra options go to `sgam bench refine`)
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -c 'import numpy' 2>/dev/null || python3 -m pip install -q numpy
SGAM=${SGAM:-target/release/sgam}
[ -x "$SGAM" ] || cargo build --release -p sgam
peer=$(python3 - <<'PY'
import time, numpy as np
n = 1024
a = np.random.rand(n, n).astype(np.float32); b = np.random.rand(n, n).astype(np.float32)
a @ b
ts = []
for _ in range(15):
    t = time.perf_counter(); a @ b; ts.append(time.perf_counter() - t)
ts.sort()
print(2 * n**3 / ts[len(ts) // 2] / 1e9)
PY
)
line=$("$SGAM" bench refine --json --iterations 10 "$@")
echo "$line"
python3 - "$peer" "$line" <<'PY'
import json, sys
peer = float(sys.argv[1]); r = json.loads(sys.argv[2])["extra"]
print(f"numpy/OpenBLAS 1024^3 GEMM: {peer:.1f} GFLOP/s; burn GEMM: {r['gemm_1024_gflops']:.1f} GFLOP/s "
      f"({r['gemm_1024_gflops'] / peer:.2f}x of numpy)")
print(f"model: {r['gflop_per_refine']:.2f} GFLOP per refine at {r['achieved_gflops']:.1f} GFLOP/s = "
      f"{r['achieved_gflops'] / peer:.2f}x of the machine's best GEMM (bar: 0.40)")
PY
