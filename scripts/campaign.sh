#!/usr/bin/env bash
# Fits the results campaign's missing cells in its order (the commands docs/results.md lists; each
# skips the cells already recorded in results/), then rewrites docs/results.md. Stop it with Ctrl-C:
# running cells checkpoint, and the next run resumes them.
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/python -c "from cvqpg.campaign.results import CAMPAIGN; print('\n'.join(c for g in CAMPAIGN for c in g.commands))" |
while read -r command; do
    echo "== $command"
    .venv/bin/$command --quiet "$@" </dev/null
done
.venv/bin/cvqpg results --overwrite
