#!/usr/bin/env bash
# Check diagnose's shareable report in a real browser: simulate a train whose brakes have lost
# 30 % (scenario metro_degraded, 300 s, no ground truth), diagnose it, write report.html and
# render the whole page at 1280 px in headless Chromium (Debian's package: apt-get install -y
# chromium) into docs/diagnose_report.png, the screenshot docs/diagnose.md shows; then the same
# for fleet's page on a small simulated fleet (4 trains x 2 runs of 200 s, one hidden map
# error, one train with degrading brakes) into docs/fleet_report.png, the screenshot
# docs/fleet.md shows, with that run's report.md and plots as docs/fleet_report_example.md and
# docs/fleet_*.png.
# Usage: ./run exec bash scripts/check_report.sh [OUT_DIR (default out/report_demo)]
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-out/report_demo}"
rm -rf "$out"
mkdir -p "$out"
python -m train_sim.generate --scenario metro_degraded --measured --duration 300 --out "$out/bag"
diagnose --bag "$out/bag" --line ros_ws/src/train_core/config/lines/metro_demo.yaml \
    --train ros_ws/src/train_core/config/trains/metro_b6.yaml --out "$out/diag" --quiet
python -m train_estimation.tools.report_html "$out/diag" --screenshot docs/diagnose_report.png \
    --size 1280
python -m train_sim.fleet "$out/fleet_world" --trains 4 --runs 2 --degraded 1 --stops 1
fleet --manifest "$out/fleet_world/manifest.csv" --out "$out/fleet" --workers 2 --no-dashboard
python -m train_estimation.tools.report_html "$out/fleet" --screenshot docs/fleet_report.png \
    --size 1280
for p in line_north line_south trends; do cp "$out/fleet/$p.png" "docs/fleet_$p.png"; done
sed -E 's/\]\((line_north|line_south|trends)\.png\)/](fleet_\1.png)/' "$out/fleet/report.md" \
    >docs/fleet_report_example.md
