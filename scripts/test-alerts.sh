#!/usr/bin/env bash
# The Prometheus alerts (deploy/prometheus/alerts.yaml) checked by promtool and unit-tested on
# recorded series (deploy/prometheus/alerts_test.yaml): each alert fires on the series that
# should raise it and stays quiet on a healthy job's. Needs promtool (Debian: `prometheus`).
set -euo pipefail
cd "$(dirname "$0")/../deploy/prometheus"
command -v promtool >/dev/null || { echo "test-alerts: no promtool (apt-get install prometheus)" >&2; exit 1; }
promtool check rules alerts.yaml
promtool test rules alerts_test.yaml
