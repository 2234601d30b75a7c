#!/usr/bin/env bash
# Peer benchmark for the map (issue: TSDF fusion bar): fuse the same RGB-D sequence with
# `sgam fuse` and with Open3D's VoxelBlockGrid in one run, and compare time, vertex count and
# mesh-to-mesh distance. Installs the peer (open3d-cpu, libusb) itself; tests never do.
#
# Usage: [ROUNDS=3] bench/fuse_vs_open3d.sh [SEQ_DIR] [OUT_DIR]   (medians over ROUNDS interleaved runs)
#   SEQ_DIR defaults to ../shared/data/7scenes-redkitchen-50 (2 cm voxels, 8 cm truncation, 4 m cut)
set -euo pipefail
cd "$(dirname "$0")/.."
SEQ=${1:-../shared/data/7scenes-redkitchen-50}
OUT=${2:-target/bench-fuse}
PEER=${PEER_SCRIPT:-../shared/bench/open3d_vbg_fuse.py}
mkdir -p "$OUT"
if ! python3 -c "import open3d" 2>/dev/null; then
  (apt-get update -qq && apt-get install -y -qq libusb-1.0-0) >/dev/null 2>&1 || true
  pip install -q open3d-cpu
fi
cargo build --release -q -p sgam
# Ours twice per round: frames read one at a time (the default) and --preload (frames decoded
# up front, as the peer script does: the like-for-like timing).
ROUNDS=${ROUNDS:-3}
for run in $(seq 1 "$ROUNDS"); do
  ./target/release/sgam fuse "$SEQ" --voxel-size 0.02 --trunc-voxels 4 --depth-max 4.0 \
      --out "$OUT/sgam.ply" --stats-json "$OUT/sgam-$run.json" 2>/dev/null
  ./target/release/sgam fuse "$SEQ" --voxel-size 0.02 --trunc-voxels 4 --depth-max 4.0 --preload \
      --out "$OUT/sgam-preload.ply" --stats-json "$OUT/sgam-preload-$run.json" 2>/dev/null
  python3 "$PEER" "$SEQ" --voxel 0.02 --trunc-mult 4 --depth-max 4.0 --out "$OUT/open3d.ply" > "$OUT/open3d-$run.json"
done
python3 - "$OUT" "$ROUNDS" <<'PY'
import json, sys, statistics as st
out, rounds = sys.argv[1], range(1, int(sys.argv[2]) + 1)
s = [json.load(open(f"{out}/sgam-{r}.json")) for r in rounds]
p = [json.load(open(f"{out}/sgam-preload-{r}.json")) for r in rounds]
o = [json.loads(open(f"{out}/open3d-{r}.json").read().strip().splitlines()[-1]) for r in rounds]
ours = st.median(x["integrate_plus_mesh_ms_per_frame"] for x in s)
ours_pre = st.median(x["integrate_plus_mesh_ms_per_frame"] for x in p)
peer = st.median(x["integrate_plus_mesh_ms_per_frame"] for x in o)
print(json.dumps({
  "frames": s[0]["frames"], "rounds": len(s),
  "sgam_integrate_ms_per_frame": st.median(x["integrate_ms_per_frame"] for x in s),
  "sgam_mesh_ms_per_frame": st.median(x["mesh_ms_per_frame"] for x in s),
  "sgam_integrate_plus_mesh_ms_per_frame": ours,
  "open3d_integrate_ms_per_frame": st.median(x["integrate_ms_per_frame"] for x in o),
  "open3d_integrate_plus_mesh_ms_per_frame": peer,
  "ratio_sgam_over_open3d": ours / peer,
  "sgam_preload_integrate_plus_mesh_ms_per_frame": ours_pre,
  "ratio_sgam_preload_over_open3d": ours_pre / peer,
  "sgam_vertices": s[0]["vertices"], "open3d_vertices": o[0]["vertices"],
  "vertex_ratio": s[0]["vertices"] / o[0]["vertices"],
}))
PY
./target/release/sgam eval mesh "$OUT/sgam.ply" "$OUT/open3d.ply" --json
