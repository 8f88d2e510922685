#!/usr/bin/env bash
# Rewrites docs/results.md from results/ and stages it with the records of every finished cell
# (a cell is finished once its metrics.json exists, or its rd.json in a rate–distortion grid; unfinished
# cells are refitted, never committed).
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/cvqpg results --overwrite
for cell in results/*/cells/*/; do
    case "$cell" in
        results/compression*) record=rd.json ;;
        *) record=metrics.json ;;
    esac
    if [ -f "$cell/$record" ]; then
        git add "$cell"
    fi
done
git add docs/results.md
git status --short -- results docs/results.md
