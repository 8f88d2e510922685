#!/usr/bin/env bash
# Creates .venv and installs cvqpg with its test tools. torch comes first and pinned: an open
# range would pull a multi-GB CUDA build. odak (test-only cross-check) is installed without its
# GUI/plotting dependencies.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
. .venv/bin/activate
python -m pip install --quiet --upgrade pip
python -m pip install --quiet torch==2.13.0
python -m pip install --quiet -e ".[test]"
python -m pip install --quiet --no-deps odak==0.2.7
