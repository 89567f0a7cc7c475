#!/usr/bin/env bash
# Regenerates the sample recording bags/sim_room (rosbag2, mcap with zstd chunks) and its
# ground-truth mesh bags/sim_room_gt.ply from the simulator. Deterministic: the same bytes each run
# on one machine, the same up to the last bits of the poses on another kind of CPU
# (test/ros/test_sample_bag.py checks the bag against a regenerated prefix, and, marked slow, the
# whole regeneration).
#   seed 2024: a 3.4 x 3.3 m room with shelves, boxes and a cylinder, some texture-poor surfaces;
#   the device turns through ~160 degrees, so most of the room is seen
#   4 s: ToF 15 Hz (16UC1 mm), stereo 20 Hz (32FC1 m + rgb8), poses 100 Hz per sensor
# OUT=DIR writes DIR/sim_room and DIR/sim_room_gt.ply instead of bags/ (to compare without touching bags/).
set -euo pipefail
cd "$(dirname "$0")/.."
SEED=${SEED:-2024}
DURATION=${DURATION:-4}
OUT=${OUT:-bags}
mkdir -p "$OUT"
rm -rf "$OUT/sim_room" "$OUT/sim_room_gt.ply"
.venv/bin/senfunet simulate --seed "$SEED" --duration "$DURATION" --tof-rate 15 --stereo-rate 20 \
  --bag "$OUT/sim_room" --storage mcap --gt "$OUT/sim_room_gt.ply" --no-progress
du -sh "$OUT/sim_room" "$OUT/sim_room_gt.ply"
