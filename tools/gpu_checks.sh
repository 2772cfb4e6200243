#!/usr/bin/env bash
# The checks that need a CUDA GPU, for a machine with PyTorch built for CUDA (a GPU box
# without PyPI included): run from the repository root. Results of the first run, on an H100:
# docs/reports/2026-11-25-h100.md; what each part brings back: docs/gpu_checks.md.
#
#   make gpu-wheels                        # on a machine with PyPI: gsplat's wheel into .whl/
#   bash tools/gpu_checks.sh PART [OUT]    # on the GPU machine (carry .whl there)
# Where one job may run at most ten minutes, run the parts as jobs on one machine (carry .whl;
# PART may list several, comma-separated), most wanted first. Times are estimates from the
# first H100 run (ODG-T trained at 2.98 s a step then; torch.compile took ~90 s per model):
#   0. first           one call on a bare machine, at most 7 minutes by construction (each
#                      check under its own time limit, skipped when it no longer fits; the
#                      limits add up to the bound, which CHECK=parse checks), no gsplat build,
#                      at most 8 files back: the query budgets as CUDA graphs (ODG-T, ODG-L),
#                      the training step at 256 x 704 (waits, seconds per sample, batch 1
#                      and 4), FlexAttention at ODG-T's and ODG-L's sizes, ODG-T's compiled
#                      node step as one CUDA graph
#   1. build,speed     gsplat JIT (90 s); 3 ODG-T runs + odg_cpu, 12 steps each (~5 min)
#   2. node_t          4 compiles of ODG-T's step (~6-8 min)
#   3. profile,compile census + profiler (~1 min); --compile (~3 min), checkpointing (~1 min)
#   4. node_cpu,aoti   ~3 min; AOTInductor export and load (~3 min)
#   5. node_l          ~6-8 min
#   6. tests,train     ~2 min; ~3 min
#   7. node            odg demo (~2 min) and the node's overhead (~1 min)
#   8. bench,sweep     64 s, ~8 min (7 before the three budget rows); 9. presets  ~7 min
#                      (two more ODG-L compiles: estimate)
#
# PART ("all" runs every one in this order):
#   first    the first call on a machine (above): OUT holds first.tar.gz (every check's
#            JSON and log, checks.jsonl: each check's status and time), summary.md and
#            summary.json (the figures against their targets, readable on their own) and
#            gpu_checks.log; see docs/gpu_checks.md
#   build    gsplat's CUDA kernels, JIT-compiled into .torch_extensions/ (kept for the next
#            parts on the same machine), and what the machine is
#   tests    the tests that only run on CUDA: gsplat against our renderer (values and
#            gradients), training with gsplat, nvJPEG decoding of camera sets, the prefetcher's
#            side-stream uploads, --compile's losses against eager's (Inductor), the node's
#            step in every mode against eager (the AOTInductor file compiles for the CPU:
#            `make test-torch211` runs it on the GPU machines' torch)
#   train    the shipped checkpoint scored on CUDA and on the CPU (the same grid, to float
#            noise); odg_cpu and ODG-T trained 12 steps with our renderer and gsplat's
#   speed    seconds per training step: ODG-T at batch 1, 2 and 4, odg_cpu at batch 1
#            (--log-every 4), the GPU's utilisation sampled meanwhile (nvidia-smi)
#   profile  odg profile train on CUDA: census, kernel time against wall time (ODG-T, odg_cpu)
#   compile  ODG-T trained a few steps with --compile, then with --checkpoint-backbone
#   node_t   odg bench --compile eager,compiled,graphs --precision fp32,bf16: ODG-T at
#   node_l   6 x 256 x 704, 8 frames (random weights: timing and bf16 error); ODG-L the same;
#   node_cpu the shipped odg_cpu on the one-scene world's keyframes
#   aoti     odg export --aoti of the shipped odg_cpu on CUDA, and its load time against the
#            compile (odg bench --compiled-step)
#   node     the node end to end (odg demo --device cuda: needs ROS 2's Python packages) and
#            the node's own overhead per set (python -m tools.measure_node_overhead)
#   bench    one online step of ODG-T and ODG-L at paper resolution, eager, per stage
#   sweep    speed against error of the shipped checkpoint (odg bench --sweep)
#   presets  the same for ODG-T and ODG-L at paper resolution (random weights: timing only),
#            ODG-L with CUDA graphs also at query budgets 0.6 and 0.35
# Every part makes what it needs (the one-scene world, random ResNet-50 weights for the
# frozen presets) unless an earlier part on the machine did. Results: JSON, CSV, logs and
# PNGs in OUT (default out/gpu), and the whole output in OUT/gpu_checks.log;
# `python -m tools.gpu_report OUT` turns them into the tables of a report.
# DEVICE=cpu runs the same commands on the CPU (the CUDA tests skip): how this script is
# checked without a GPU. CHECK=parse runs nothing: each command line is recorded, and at the
# end its options are parsed by the command's own parser (pytest lines: collected, at least one
# test selected), so that the script is checked in seconds (test/tools/test_gpu_checks.py).
set -uo pipefail
cd "$(dirname "$0")/.."
PART=${1:-all}
OUT=${2:-${OUT:-out/gpu}}
DEVICE=${DEVICE:-cuda}
CHECK=${CHECK:-run}
PY=${PYTHON:-python3}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
export TORCH_EXTENSIONS_DIR="$PWD/.torch_extensions" MAX_JOBS=${MAX_JOBS:-$(nproc)}
exec > >(tee -a "$OUT/gpu_checks.log") 2>&1
failed=0
COMMANDS="$OUT/commands.jsonl"   # CHECK=parse: the command lines, checked at the end
[ "$CHECK" = parse ] && : > "$COMMANDS"

say() { echo "gpu_checks: $*"; }
step() {  # step NAME command...: run, time, keep going when it fails (each part says so)
    local name=$1 start=$SECONDS
    shift
    say "$name: $*"
    if "$@"; then say "$name: ok in $((SECONDS - start)) s"
    else say "$name: FAILED (exit $?) after $((SECONDS - start)) s"; failed=1; fi
}
record() {  # CHECK=parse: keep the command line (one JSON list a line) instead of running it
    $PY -c 'import json, sys; print(json.dumps(sys.argv[1:]))' "$@" >> "$COMMANDS"
}
odg() {
    if [ "$CHECK" = parse ]; then record odg "$@"; else $PY -m odg_ros.commands "$@"; fi
}
tool() {  # tool tools.NAME ARGS...: python -m tools.NAME
    if [ "$CHECK" = parse ]; then record "$@"; else $PY -m "$@"; fi
}
tests() {  # tests PYTEST-ARGS...
    if [ "$CHECK" = parse ]; then record pytest "$@"; else $PY -m pytest "$@"; fi
}
into() {  # into FILE command...: the command's stdout into FILE
    local file=$1
    shift
    if [ "$CHECK" = parse ]; then "$@"; else "$@" > "$file"; fi
}
GPU_SAMPLER=
gpu_sampling() {  # gpu_sampling FILE | gpu_sampling stop: nvidia-smi every 200 ms, if present
    if [ "$1" = stop ]; then
        [ -n "$GPU_SAMPLER" ] && kill "$GPU_SAMPLER" 2>/dev/null
        GPU_SAMPLER=
    elif [ "$CHECK" = run ] && command -v nvidia-smi >/dev/null; then
        nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used,power.draw \
            --format=csv,nounits -lms 200 > "$1" &
        GPU_SAMPLER=$!
    fi
}
trap 'gpu_sampling stop' EXIT

# gsplat from the carried wheel where the machine has none (a GPU box may reach no registry)
if [ "$CHECK" = run ] && ! $PY -c "import gsplat" 2>/dev/null; then
    if compgen -G ".whl/gsplat-*.whl" >/dev/null; then
        $PY -m pip install -q --no-index --no-deps --no-compile --target /tmp/odg_site .whl/*.whl \
            && export PYTHONPATH="$PYTHONPATH:/tmp/odg_site"
    else
        say "gsplat is not installed and .whl/ has no wheel of it: run 'make gpu-wheels' where"
        say "PyPI is reachable and carry .whl"
    fi
fi
if [ "$DEVICE" = cuda ]; then
    # build for this GPU only: the JIT compile of every architecture takes many minutes
    arch=$($PY -c "import torch; print('%d.%d' % torch.cuda.get_device_capability())") || {
        say "no CUDA device for PyTorch here (DEVICE=cpu runs the CPU stand-in)"; exit 2; }
    export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-$arch}
fi

machine() {  # what the machine is: OUT/machine.json
    $PY -m tools.gpu_report --machine > "$OUT/machine.json"
    cat "$OUT/machine.json"
    command -v nvidia-smi >/dev/null && nvidia-smi > "$OUT/nvidia-smi.txt"
    return 0
}

part_build() {
    machine
    if [ "$DEVICE" = cuda ]; then
        step "gsplat CUDA kernels (JIT)" $PY -c "from gsplat.cuda._backend import _C; assert _C is not None, 'gsplat found no CUDA toolkit'"
    fi
}

part_tests() {
    step "CUDA tests" tests -q -p no:cacheprovider -rs --timeout 900 \
        --junitxml="$OUT/tests.xml" test/render/test_render_gsplat.py test/render/test_render.py \
        test/losses/test_loss_render.py test/train/test_train.py -k "cuda or gsplat or render"
    step "CUDA tests of the data path, --compile and the node's step" tests -q -p no:cacheprovider -rs \
        --timeout 900 --junitxml="$OUT/tests_node.xml" test/online/test_online_images.py \
        test/data/test_data_path.py test/train/test_train_options.py test/online/test_online_step.py \
        test/online/test_online_predictor.py
}

part_bench() {
    local runs=out/gpu_bench p k iters=20 warmup=3
    [ "$DEVICE" = cpu ] && iters=1 warmup=0
    rm -rf "$runs"; mkdir -p "$runs"
    for p in odg_t odg_l; do
        for k in fp32 bf16; do
            [ "$DEVICE" = cpu ] && [ "$p" = odg_l ] && continue  # 16 s a step on a CPU
            step "bench $p $k" into "$runs/$p-$k.json" odg bench --preset $p --device $DEVICE \
                --precision $k --iters $iters --warmup $warmup --json
        done
    done
    for k in fp32 bf16; do
        step "bench odg_cpu (shipped) $k" into "$runs/odg_cpu_shipped-$k.json" odg bench \
            --checkpoint model/odg_cpu.pt --device $DEVICE --precision $k --iters $iters \
            --warmup $warmup --json
    done
    [ "$CHECK" = parse ] && return
    $PY -c "import json, sys; json.dump({p.split('/')[-1][:-5]: json.load(open(p))
        for p in sys.argv[1:]}, sys.stdout, indent=1)" "$runs"/*.json > "$OUT/bench.json"
}

WORLD=out/gpu_world  # one 4 s scene (8 keyframes) the training worlds never used
world() {
    [ -f "$WORLD/infos_all.pkl" ] || [ -n "${WORLD_RECORDED:-}" ] && return
    WORLD_RECORDED=$([ "$CHECK" = parse ] && echo 1)
    [ "$CHECK" = run ] && rm -rf "$WORLD"
    step "one-scene world" odg synth --out "$WORLD" --scenes 1 --seconds 4 --seed 1000
    step "infos" odg prepare --dataroot "$WORLD" --out "$WORLD/infos_all.pkl" --split all
}

R50=out/gpu_resnet50_random.pth  # stands in for ImageNet weights: the frozen presets need some
resnet50_weights() {
    [ -f "$R50" ] || [ "$CHECK" = parse ] && return
    mkdir -p "$(dirname "$R50")"
    step "random ResNet-50 weights (torchvision layout)" $PY -c "
import os, sys, torch
from odg_ros.network.backbone import ResNet
torch.manual_seed(0)
torch.save(ResNet('resnet50').state_dict(), sys.argv[1] + '.part')
os.replace(sys.argv[1] + '.part', sys.argv[1])" "$R50"
}

part_sweep() {
    world
    local limit=8 isolate=--no-isolate  # CUDA peak memory is reset per configuration
    [ "$DEVICE" = cpu ] && limit=2 isolate=
    step "sweep of the shipped checkpoint" odg bench --sweep \
        --data "$WORLD/infos_all.pkl" --checkpoint model/odg_cpu.pt --device "$DEVICE" \
        --out "$OUT/sweep_shipped" --limit $limit --iters 3 $isolate
}

part_presets() {
    world
    local presets=config/sweep_presets_gpu.json isolate=--no-isolate
    [ "$DEVICE" = cpu ] && presets=config/sweep_presets_gpu_standin.json isolate=
    step "sweep of ODG-T and ODG-L" odg bench --sweep --configs "$presets" \
        --data "$WORLD/infos_all.pkl" --checkpoint model/odg_cpu.pt --device "$DEVICE" \
        --out "$OUT/sweep_presets" --limit 2 --iters 3 $isolate
}

train_run() {  # train_run NAME PRESET STEPS ARGS...: odg train, its log kept as OUT/train_NAME.csv
    local name=$1 preset=$2 steps=$3 runs=out/gpu_runs weights=
    shift 3
    [ "$preset" != odg_cpu ] && weights="--backbone-weights $R50"
    [ "$CHECK" = run ] && rm -rf "$runs/$name"
    step "train $name" odg train --preset "$preset" --data "$WORLD/infos_all.pkl" \
        --out "$runs/$name" --steps "$steps" --checkpoint-every 1000 --device "$DEVICE" \
        --workers 4 $weights "$@"
    [ "$CHECK" = run ] && cp "$runs/$name/train_log.csv" "$OUT/train_$name.csv" 2>/dev/null
    return 0
}

part_train() {
    world
    resnet50_weights
    for d in "$DEVICE" cpu; do
        step "eval on $d" into "$OUT/eval_$d.json" odg eval --checkpoint model/odg_cpu.pt \
            --data "$WORLD/infos_all.pkl" --device $d --json
        [ "$DEVICE" = cpu ] && break
    done
    local renderers=torch
    [ "$DEVICE" = cuda ] && renderers="torch gsplat"
    for preset in odg_cpu odg_t; do
        for r in $renderers; do
            train_run "${preset}_$r" $preset 12 --renderer $r --log-every 4
        done
        [ "$DEVICE" = cpu ] && [ "$CHECK" = run ] && break  # ODG-T: tens of seconds a step
    done
}

part_speed() {  # seconds per step, --log-every 4: two reads after the first (warm-up) one
    world
    resnet50_weights
    gpu_sampling "$OUT/gpu_util_speed.csv"
    train_run odg_cpu_b1 odg_cpu 12 --log-every 4
    for b in 1 2 4; do
        train_run odg_t_b$b odg_t 12 --batch-size $b --log-every 4
        [ "$DEVICE" = cpu ] && [ "$CHECK" = run ] && break
    done
    gpu_sampling stop
}

part_profile() {
    world
    resnet50_weights
    step "profile ODG-T" odg profile train --preset odg_t --backbone-weights "$R50" \
        --data "$WORLD/infos_all.pkl" --device "$DEVICE" --json "$OUT/profile_odg_t.json"
    step "profile odg_cpu" odg profile train --preset odg_cpu --data "$WORLD/infos_all.pkl" \
        --device "$DEVICE" --json "$OUT/profile_odg_cpu.json"
}

part_compile() {
    world
    resnet50_weights
    gpu_sampling "$OUT/gpu_util_compile.csv"
    train_run odg_t_compile odg_t 12 --compile --log-every 4
    train_run odg_t_checkpointed odg_t 12 --checkpoint-backbone --log-every 4
    gpu_sampling stop
}

node_bench() {  # node_bench NAME ARGS...: the node's step in each of MODES, fp32 and bf16
    local name=$1 modes=${MODES:-eager,compiled,graphs} iters=20 warmup=3
    shift
    [ "$DEVICE" = cpu ] && [ "$CHECK" = run ] && modes=eager,compiled iters=2 warmup=1
    step "node step $name" into "$OUT/node_$name.json" odg bench --compile $modes \
        --precision fp32,bf16 --device "$DEVICE" --iters $iters --warmup $warmup --json "$@"
}

# first: one call on a bare machine, bounded. Each check runs under `timeout` with its own
# limit, and only if that limit still fits in what is left of FIRST_LIMIT (counted from the
# script's start); the last one, ODG-T's compile, gets all that is left. Each writes into
# WORK, and after each check WORK is packed into OUT (first.tar.gz) with a summary readable on
# its own (summary.md, summary.json): what the checks had made comes back even if the call is
# cut. CHECK=parse adds the limits up (tools/gpu_checks_parse.py): the bound of the wall time.
FIRST_LIMIT=420      # seconds: the part's wall time at most, from the script's start
FIRST_FILES=8        # files in OUT at most (what a GPU call hands back)
STARTUP=15           # seconds before the first check (bash, the gsplat and GPU probes)
KILL_GRACE=2         # seconds between timeout's TERM and KILL
PACK_LIMIT=5         # seconds for each packing of WORK into OUT
WORK=out/gpu_first
bounded() {  # bounded NAME SECONDS|rest:MIN [--into FILE] odg|tool ARGS...: one check of first
    local name=$1 limit=$2 into= kind start=$SECONDS left status rc
    shift 2
    if [ "$1" = --into ]; then into=$2; shift 2; fi
    kind=$1
    shift
    if [ "$CHECK" = parse ]; then
        $kind "$@"
        record bound first "$name" "$limit" "$((KILL_GRACE + PACK_LIMIT))"
        return
    fi
    left=$((FIRST_LIMIT - SECONDS - KILL_GRACE - PACK_LIMIT))
    if [[ $limit == rest:* ]]; then   # the time left, if at least MIN
        [ "$left" -ge "${limit#rest:}" ] && limit=$left || limit=${limit#rest:}
    fi
    if [ "$left" -lt "$limit" ]; then
        say "$name: skipped: its $limit s do not fit in the $left s left"
        status="skipped (no time left)"
    else
        local command=($PY -m odg_ros.commands "$@")
        [ "$kind" = tool ] && command=($PY -m "$@")
        say "$name (at most $limit s): ${command[*]}"
        if [ -n "$into" ]; then
            timeout -k $KILL_GRACE "$limit" "${command[@]}" > "$into"
        else
            timeout -k $KILL_GRACE "$limit" "${command[@]}"
        fi
        rc=$?
        case $rc in
            0) status=ok ;;
            124|137) status="timed out after $limit s"; failed=1 ;;
            *) status="failed (exit $rc)"; failed=1 ;;
        esac
        say "$name: $status in $((SECONDS - start)) s"
    fi
    pack_first "$name" "$status" "$((SECONDS - start))" "$limit"
}
pack_first() {  # pack_first [CHECK STATUS SECONDS LIMIT]: the check's line into
    # WORK/checks.jsonl, then WORK -> OUT/first.tar.gz, OUT/summary.{md,json} (each whole)
    timeout -k 1 $PACK_LIMIT bash -c '
        [ $# -gt 3 ] && $3 -c "import json, sys; print(json.dumps(dict(zip(
            (\"check\", \"status\", \"seconds\", \"limit\"), sys.argv[1:]))))" \
            "${@:4}" >> "$1/checks.jsonl"
        tar -czf "$2/first.tar.gz.part" --exclude=./world -C "$1" . && mv "$2/first.tar.gz.part" "$2/first.tar.gz"
        $3 -m tools.gpu_report "$1" --first --summary-json "$2/summary.json.part" \
            > "$2/summary.md.part" && mv "$2/summary.json.part" "$2/summary.json" \
            && mv "$2/summary.md.part" "$2/summary.md"' _ "$WORK" "$OUT" "$PY" "$@" \
        || say "packing the results failed (the last complete pack is in $OUT)"
}

part_first() {
    rm -rf "$WORK"; mkdir -p "$WORK"
    : > "$WORK/checks.jsonl"
    [ "$CHECK" = parse ] && record bound first startup "$STARTUP" 0
    local iters=20 presets=(odg_t odg_l) flex=(600 4800) node=(--preset odg_t --frames 8)
    local size=(--image-size 256 704 --frames 8 --render-pixels 512) modes=eager,graphs
    local world=$WORK/world
    if [ "$DEVICE" = cpu ] && [ "$CHECK" = run ]; then   # a dry run of the plumbing
        iters=2 presets=(odg_cpu) flex=(48) node=(--preset odg_cpu --frames 2) modes=eager
        size=(--image-size 32 88 --frames 2 --render-pixels 64)
    fi
    bounded machine 10 --into "$WORK/machine.json" tool tools.gpu_report --machine
    # CudaGraphStep per query budget: full, auto (one graph per rung), 0.6 and 0.35, each
    # against eager; the decoder at each rung; auto against full on the open road
    bounded "query budgets as CUDA graphs" 65 tool tools.budget_graphs --preset "${presets[@]}" \
        --precision bf16 --device "$DEVICE" --iters $iters "${size[@]:0:5}" \
        --json "$WORK/budgets.json"
    # the training step at the size users train, on a 2 s world (4 keyframes): host waits
    # (sync-debug mode and the census on CUDA) and seconds per sample at batch 1 and 4
    bounded world 25 odg synth --out "$world" --scenes 1 --seconds 2 --seed 1000
    bounded infos 10 odg prepare --dataroot "$world" --out "$world/infos_all.pkl" --split all
    bounded "training step, batch 1 and 4" 90 tool tools.sync_debug_step \
        --data "$world/infos_all.pkl" --backbone-weights random --batch-size 1 4 \
        --timed-steps 3 --device "$DEVICE" --no-cpu-census "${size[@]}" \
        --json "$WORK/training_step.json"
    # DaS attention compiled with FlexAttention at ODG-T's and ODG-L's sizes, bf16 autocast
    bounded FlexAttention 40 tool tools.flex_attention_check --queries "${flex[@]}" \
        --device "$DEVICE" --iters $iters --json "$WORK/flex_attention.json"
    # ODG-T's node step compiled and replayed as one CUDA graph, bf16: a compile of minutes
    bounded "node step" rest:90 --into "$WORK/node_step.json" odg bench --compile $modes \
        --precision bf16 --device "$DEVICE" --iters $((iters * 2)) --warmup 3 --json \
        "${node[@]}"
    if [ "$CHECK" = parse ]; then
        pack_first          # what the packing leaves in OUT, counted
        record limit first "$FIRST_LIMIT" "$FIRST_FILES" \
            "$(find "$OUT" -type f ! -name commands.jsonl | wc -l)"
    fi
}

part_node_t() { node_bench odg_t --preset odg_t --frames 8; }
part_node_l() { node_bench odg_l --preset odg_l --frames 8; }
part_node_cpu() {
    world
    node_bench odg_cpu --checkpoint model/odg_cpu.pt --data "$WORLD/infos_all.pkl"
}

part_aoti() {
    world
    local file=out/gpu_runs/odg_cpu_$DEVICE.pt2 modes=eager,compiled,graphs
    [ "$DEVICE" = cpu ] && [ "$CHECK" = run ] && modes=eager,compiled
    mkdir -p out/gpu_runs
    step "odg export --aoti (odg_cpu)" odg export --checkpoint model/odg_cpu.pt --aoti "$file" \
        --device "$DEVICE"
    step "node step from the exported file" into "$OUT/node_odg_cpu_aoti.json" odg bench \
        --compile $modes --compiled-step "$file" --checkpoint model/odg_cpu.pt \
        --data "$WORLD/infos_all.pkl" --device "$DEVICE" --iters 20 --warmup 3 --json
}

part_node() {
    step "odg demo (the node on $DEVICE)" into "$OUT/demo.json" odg demo --out out/gpu_demo \
        --device "$DEVICE" --rate 1 --json
    [ "$CHECK" = run ] && cp out/gpu_demo/demo.png out/gpu_demo/node.log "$OUT/" 2>/dev/null
    step "node overhead" into "$OUT/node_overhead.txt" tool tools.measure_node_overhead \
        --sets 30 --model-ms 15
}

PARTS="first build tests train speed profile compile node_t node_l node_cpu aoti node bench sweep presets"
[ "$PART" = all ] && PART=${PARTS// /,}
for part in ${PART//,/ }; do
    if [[ " $PARTS " != *" $part "* ]]; then
        say "unknown part '$part' (one or more, comma-separated, of: $PARTS; or all)"; exit 2
    fi
done
for part in ${PART//,/ }; do
    say "part $part"
    "part_$part"
done
if [ "$CHECK" = parse ]; then
    step "command lines parse" $PY -m tools.gpu_checks_parse "$COMMANDS"
fi
say "results in $OUT: $(ls "$OUT" | tr '\n' ' ')"
exit $failed
