#!/usr/bin/env bash
# Every GPU figure of issue #24's targets, measured in one command on a machine with one CUDA GPU.
#
#   benchmarks/gpu.sh OUT [PART ...]     PART: env stage fits fits4k bento bench (default: all, in that order)
#
# Writes into OUT (8 files at most, so that they all come back from a lent machine):
#   env.txt          GPU, driver, torch, CPU cores
#   stage.txt/.json  benchmarks/step.py --device cuda: the stage table against the GPU FFT floor, full-grid
#                    propagation (auto's choice on CUDA) and a stage with the pruned transforms in its place,
#                    with one round of the PyTorch reference rasterizer
#   fits.txt         whole 2000-step fits of RGB 20% and grayscale 10% at 640×480: the first fit apart, fit
#                    loop, peak torch.cuda.max_memory_allocated, PSNR
#   fits4k.txt       the same for RGB 20% at 3840×2160
#   bento.txt        bento RGB 20%, 2000 steps, on the GPU and on the CPU of the same machine: both PSNRs
#                    (needs $SCENES/bento: image.* and depth.png; SCENES defaults to ../shared/scenes)
#   bench.txt        `cvqpg bench --device cuda --jobs K` for K = 1, 2, 4 on one small grid: wall time each
# A part whose file is already in OUT is skipped, so a run cut short continues where it stopped, and the
# parts can be run one call at a time where a call's time is limited (fits4k and bento take longest).
# PYTHON picks the interpreter (default: python); the run folders go to a temporary folder.
set -euo pipefail

out=$(realpath -m "${1:?usage: benchmarks/gpu.sh OUT [env|stage|fits|fits4k|bento|bench ...]}")
shift
parts=("$@")
[ ${#parts[@]} -eq 0 ] && parts=(env stage fits fits4k bento bench)
python=${PYTHON:-python}
scenes=$(realpath -m "${SCENES:-../shared/scenes}")
cd "$(dirname "$0")/.."
mkdir -p "$out"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

cvqpg() { "$python" -m cvqpg.cli "$@"; }

part_env() {
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv || true
    "$python" -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda, \
'device', torch.cuda.get_device_name(0))"
    echo "cpu cores: $(nproc)"
    echo "commit: $(git rev-parse HEAD 2>/dev/null || echo unknown)"
}

part_stage() {
    "$python" benchmarks/step.py --device cuda --reference-rounds 1 --json "$out/stage.json"
}

part_fits() {
    "$python" benchmarks/step.py --device cuda --whole-fit small --fits-only
}

part_fits4k() {
    "$python" benchmarks/step.py --device cuda --whole-fit big --fits-only
}

psnr_of() { "$python" -c "import json, sys; print(json.load(open(sys.argv[1]))['mean']['psnr'])" "$1/metrics.json"; }

part_bento() {
    local image
    image=$(ls "$scenes"/bento/image.* 2>/dev/null | head -n 1 || true)
    if [ -z "$image" ]; then
        echo "no bento scene in $scenes: set SCENES to a folder holding bento/image.* and bento/depth.png" >&2
        return 1
    fi
    for device in cuda cpu; do
        local started=$SECONDS
        cvqpg fit "$image" --depth "$scenes/bento/depth.png" --ratio 0.2 --device "$device" \
            --out "$work/bento-$device" --quiet
        echo "bento RGB 20%, 2000 steps, $device: PSNR $(psnr_of "$work/bento-$device") dB, \
$((SECONDS - started)) s wall"
    done
    "$python" -c "import sys; gpu, cpu = map(float, sys.argv[1:]); \
print(f'GPU - CPU: {gpu - cpu:+.4f} dB (target: within 0.05 dB)')" \
        "$(psnr_of "$work/bento-cuda")" "$(psnr_of "$work/bento-cpu")"
}

part_bench() {
    for jobs in 1 2 4; do
        local started=$SECONDS
        cvqpg bench --preset quick --device cuda --jobs "$jobs" --size 640 480 --steps 200 --colors rgb gray \
            --seeds 100 101 --out "$work/bench-$jobs" --quiet > "$work/bench-$jobs.log"
        echo "bench --jobs $jobs: 16 cells (quick preset, 640×480, 200 steps), $((SECONDS - started)) s wall"
    done
}

for part in "${parts[@]}"; do
    case $part in
        env) files=(env) ;;
        stage|fits|fits4k|bento|bench) files=("$part") ;;
        *) echo "unknown part $part: choose env, stage, fits, fits4k, bento or bench" >&2; exit 2 ;;
    esac
    for name in "${files[@]}"; do
        if [ -s "$out/$name.txt" ]; then
            echo "$out/$name.txt exists: skipped"
            continue
        fi
        echo "== $name"
        "part_$name" | tee "$out/$name.txt.partial"
        mv "$out/$name.txt.partial" "$out/$name.txt"
    done
done
