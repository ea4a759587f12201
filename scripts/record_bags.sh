#!/usr/bin/env bash
# Re-record the reference bags under bags/ from the live nodes (simulator, estimators, zone
# controller, recorder as separate processes). Usage: ./run exec bash scripts/record_bags.sh
set -euo pipefail
cd "$(dirname "$0")/.."
tmp=$(mktemp -d)
python -m train_bringup.main_job --scenario metro_demo --duration 120 \
    --rate-factor 10 --out "$tmp/metro"
python -m train_bringup.main_job --scenario wen2017_subway --rate-factor 10 \
    --estimators robust_filter --out "$tmp/wen"
rm -rf bags/metro_demo_short bags/wen2017_subway
cp -r "$tmp/metro/bag" bags/metro_demo_short
cp -r "$tmp/wen/bag" bags/wen2017_subway
du -sh bags/*
