#!/usr/bin/env bash
# Creates .venv (or reuses it, with the torch build already in it) and installs cvqpg in editable
# mode with its test and documentation tools, at the exact versions of constraints.txt. Then compiles the CPU
# kernels (`cvqpg compile`), so that the first fit starts at once, and the package's bytecode, which an editable
# install leaves to the first import (and which, with PYTHONDONTWRITEBYTECODE set, every process would compile
# again).
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
. .venv/bin/activate
python -m pip install --quiet --upgrade pip
python -m pip install --quiet -c constraints.txt -e ".[test,docs]"
# odak imports cv2; the headless build of OpenCV imports without the system's libGL (GUI) libraries.
python -m pip uninstall --quiet --yes opencv-python
python -m pip install --quiet --force-reinstall --no-deps -c constraints.txt opencv-python-headless
python -m compileall -q cvqpg
cvqpg compile
