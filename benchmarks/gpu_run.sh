#!/usr/bin/env bash
# A lent GPU's whole session of checks, in one command (device time is short and each start
# costs minutes).  Run from the repository root on the GPU machine:
#
#   OUT=/some/folder SCENE=.gpu_data/canclip benchmarks/gpu_run.sh
#
# 1. smoke: every CUDA path the product uses (train with the default's teacher, multi-view
#    losses, per-photo colour and pose refinement; render with depth and refocus; eval), short,
#    and the run stops here if any of it fails;
# 2. issue 5's GPU quality target: the default and larger ray batches, the authors' network and
#    the plane sweep, each given one minute at 960x540 (benchmarks/speed_accuracy.py);
# 3. issue 5's GPU frame-rate target at 1008x567 (benchmarks/render_fps.py);
# 4. where a training step and a frame spend their time (benchmarks/gpu_profile.py), and the
#    frame rate with larger render chunks.
# 5. stability: issue 4's seed spread for the default at a longer budget (STAB_STEPS, default
#    3000), its scenes packed by `python benchmarks/stability.py --pack .gpu_data/stab`.
# 6. scatter: how wide three seeds fall by chance at that budget (benchmarks/seed_scatter.py,
#    SCATTER_SEEDS, default 0-7, at STAB_STEPS), on the same packed scenes.
# STAGES picks among smoke, bench, fps, profile, stability, scatter (default: the first three).
# Python packages the machine lacks (pycolmap) travel as wheels in .whl/; the scene in
# .gpu_data/ (both ignored by git, carried by the device tool).  To prepare them, on a machine
# with the network (the GPU machine's Python was 3.12):
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#       --platform manylinux_2_28_x86_64 -d .whl pycolmap==4.2.1
#   cp -r ../shared/data/canclip .gpu_data/
# A machine that has pycolmap runs it with WHEELS=none.  Results: docs/BENCHMARKS.md, "The GPU
# targets on an NVIDIA H200".
set -u
export PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/gpu_out}
SCENE=${SCENE:-.gpu_data/canclip}
DEVICE=${DEVICE:-cuda}
MINUTES=${MINUTES:-1}
STAGES=${STAGES:-smoke,bench,fps}
METHODS=${METHODS:-fast,fast@65536,authors,classic-sweep}
mkdir -p "$OUT"
WHEELS=${WHEELS:-.whl}
if ls "$WHEELS"/*.whl >/dev/null 2>&1; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$WHEELS"/*.whl || exit 1
    export PYTHONPATH=/tmp/site
fi
python3 -c "import torch, numpy, pycolmap; print('torch', torch.__version__, 'numpy', numpy.__version__, 'pycolmap', pycolmap.__version__, torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'no GPU')" || exit 1
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.total,clocks.sm,clocks.max.sm --format=csv

step() { echo "== $(date +%T) $*"; }
smoke() {
    set -e -o pipefail
    rm -rf /tmp/smoke /tmp/smoke2 /tmp/smoke3 /tmp/models
    step "smoke: train (default) 300 steps at scale 0.25"
    python3 -m neulf_core train "$SCENE" --out /tmp/smoke --scale 0.25 --steps 300 --progress json --device "$DEVICE" | tail -3
    step "smoke: train with forced colour transforms, multi-view losses, pose refinement"
    python3 -m neulf_core train "$SCENE" --out /tmp/smoke2 --scale 0.25 --steps 60 --appearance --consistency --refine-poses \
        --progress json --device "$DEVICE" | tail -2
    step "smoke: authors' network"
    python3 -m neulf_core train "$SCENE" --out /tmp/smoke3 --scale 0.25 --steps 30 --preset authors --progress json --device "$DEVICE" | tail -1
    step "smoke: render held-out views with depth, half and full; refocus; eval"
    python3 -m neulf_core render /tmp/smoke --scene "$SCENE" --views held-out --depth --out /tmp/smoke_render --device "$DEVICE"
    python3 -m neulf_core render /tmp/smoke --scene "$SCENE" --views held-out --out /tmp/smoke_render_full --device "$DEVICE" --precision full
    python3 -m neulf_core render /tmp/smoke --scene "$SCENE" --views held-out --out /tmp/smoke_focus --device "$DEVICE" \
        --focus-pixel 120,67 --aperture 0.05
    python3 -m neulf_core eval /tmp/smoke --scene "$SCENE" --device "$DEVICE" --fit-poses
    python3 -m neulf_core render /tmp/smoke3 --scene "$SCENE" --views held-out --out /tmp/smoke_render3 --device "$DEVICE"
}
has() { [[ ",$STAGES," == *",$1,"* ]]; }
if has smoke; then
    ( smoke ) 2>&1 | tee "$OUT/smoke.log"
    [ "${PIPESTATUS[0]}" -eq 0 ] || { echo "SMOKE FAILED: the benchmarks were not run"; exit 2; }
fi

if has bench; then
step "speed against accuracy, $MINUTES min per method, 960x540"
python3 benchmarks/speed_accuracy.py --scene "$SCENE" --scale 1 --minutes "$MINUTES" --every 5 --device "$DEVICE" \
    --methods "$METHODS" --name canclip_gpu --keep-models /tmp/models 2>&1 | tee "$OUT/speed_accuracy.log"
cp docs/bench_canclip_gpu.csv docs/bench_canclip_gpu.png "$OUT"/ 2>/dev/null
fi

if has profile; then
    step "profile: training steps and frames"
    python3 benchmarks/gpu_profile.py --scene "$SCENE" --scale 1 --steps 600 --device "$DEVICE" --out "$OUT" \
        --model-out /tmp/models/profile/fast 2>&1 | grep -v USDT
    step "frames per second at 1008x567 by render chunk"
    python3 benchmarks/render_fps.py --scene "$SCENE" --model fast=/tmp/models/profile/fast --width 1008 --height 567 \
        --device "$DEVICE" --precision auto,full --chunks 262144,1048576 --repeats 30 --out "$OUT/render_fps_chunks.csv" 2>&1
fi

if has fps; then
step "frames per second at 1008x567"
models=()
for dir in /tmp/models/canclip_gpu/*; do [ -f "$dir/model.pt" ] && models+=(--model "$(basename "$dir")=$dir"); done
python3 benchmarks/render_fps.py --scene "$SCENE" "${models[@]}" --width 1008 --height 567 --device "$DEVICE" \
    --precision auto,full --repeats 30 --out "$OUT/render_fps.csv" 2>&1 | tee "$OUT/render_fps.log"
fi
if has stability; then
    # Issue 4's seed spread at a longer budget: the default's 35 configurations, three seeds,
    # STAB_STEPS steps, many runs side by side on the one GPU (a step is launch-bound, so the
    # GPU has room).  The scenes travel packed (python benchmarks/stability.py --pack
    # .gpu_data/stab, here with Blender); the run log comes back in $OUT/stability even when the
    # time limit cuts the study short, and the report covers whole configurations.
    STAB_PACK=${STAB_PACK:-.gpu_data/stab}
    STAB_ARGS=(--cache "$OUT/stability" --canclip "$STAB_PACK/canclip" --canclip-scale 1 --hci "$STAB_PACK/hci"
               --hci-scale 1 --fern /nonexistent --only "${STAB_ONLY:-views,variants,exposure,pose}" ${STAB_SCENES:+--scenes "$STAB_SCENES"} --defaults-only
               --fast-steps "${STAB_STEPS:-3000}" --docs "$OUT/stability/docs")
    mkdir -p "$OUT/stability"
    ln -sfn "$PWD/$STAB_PACK/scenes" "$OUT/stability/scenes"
    step "stability: the default's configurations at ${STAB_STEPS:-3000} steps, ${STAB_WORKERS:-15} side by side"
    timeout "${STAB_SECONDS:-500}" python3 benchmarks/stability.py "${STAB_ARGS[@]}" --by-configuration \
        --workers "${STAB_WORKERS:-15}" 2>&1 | grep -v "^rendering" | tee "$OUT/stability.log"
    pkill -f "multiprocessing.spawn" 2>/dev/null
    python3 benchmarks/stability.py "${STAB_ARGS[@]}" --report-only > "$OUT/stability/report.md" 2>&1
    rm -f "$OUT/stability/scenes"
fi
if has scatter; then
    STAB_PACK=${STAB_PACK:-.gpu_data/stab}
    mkdir -p "$OUT/scatter/docs"
    cp docs/SEED_SCATTER.md "$OUT/scatter/docs/"
    SCATTER_ARGS=(--cache "$OUT/scatter" --scenes-cache "$STAB_PACK" --canclip "$STAB_PACK/canclip" --canclip-scale 1
                  --steps "${STAB_STEPS:-3000}" --seeds "${SCATTER_SEEDS:-0-7}" --docs "$OUT/scatter/docs"
                  ${SCATTER_CONFIGURATIONS:+--configurations "$SCATTER_CONFIGURATIONS"})
    step "seed scatter at ${STAB_STEPS:-3000} steps, ${STAB_WORKERS:-15} side by side"
    timeout "${STAB_SECONDS:-500}" python3 benchmarks/seed_scatter.py "${SCATTER_ARGS[@]}" --workers "${STAB_WORKERS:-15}" 2>&1 \
        | grep -v "^rendering" | tee "$OUT/scatter.log"
    pkill -f "multiprocessing.spawn" 2>/dev/null
    python3 benchmarks/seed_scatter.py "${SCATTER_ARGS[@]}" --report-only > "$OUT/scatter/report.md" 2>&1
fi
step "done"
