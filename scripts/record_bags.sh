#!/usr/bin/env bash
# Re-record the reference bags under bags/ from the live nodes (simulator, estimators, zone
# controller, recorder as separate processes). Usage: ./run exec bash scripts/record_bags.sh
# metro_demo_short keeps every topic but the /train/odom/* copies of the estimates (the same
# estimates as nav_msgs/Odometry: three times the bag's size, and the main job records them).
set -euo pipefail
cd "$(dirname "$0")/.."
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
# metro at 2x real time: on a loaded machine 10x puts seconds of bag time between a sample and
# its estimate in the recording (the estimates are the same; their recorded latency is not)
python -m train_bringup.main_job --scenario metro_demo --duration 120 \
    --rate-factor 2 --out "$tmp/metro"
python -m train_bringup.main_job --scenario wen2017_subway --rate-factor 10 \
    --estimators robust_filter --out "$tmp/wen"
rm -rf bags/metro_demo_short bags/wen2017_subway
python - "$tmp/metro/bag" bags/metro_demo_short <<'PY'
import sys
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

src, dst = sys.argv[1:3]
with Reader(src) as r, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as w:
    out = {c.id: w.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, rihs01=c.digest)
           for c in r.connections if not c.topic.startswith("/train/odom/")}
    for c, t, raw in r.messages(connections=[c for c in r.connections if c.id in out]):
        w.write(out[c.id], t, raw)
PY
cp -r "$tmp/wen/bag" bags/wen2017_subway
du -sh bags/*
