#!/usr/bin/env bash
# The checks that need a CUDA GPU, for a machine with PyTorch built for CUDA (a GPU box
# without PyPI included): run from the repository root. Results of the first run, on an H100:
# docs/reports/2026-11-25-h100.md.
#
#   make gpu-wheels                        # on a machine with PyPI: gsplat's wheel into .whl/
#   bash tools/gpu_checks.sh PART [OUT]    # on the GPU machine (carry .whl there)
# Where one job may run at most ten minutes, run it as three jobs on the same machine (carry
# .whl along; times measured on the H100):
#   1. build (87 s), tests (29 s), train (5 min)   only these two need the gsplat build
#   2. bench (64 s), sweep (7 min)
#   3. presets (4 min: torch.compile takes ~90 s per model)
#
# PART ("all" runs every one in this order):
#   build    gsplat's CUDA kernels, JIT-compiled into .torch_extensions/ (kept for the next
#            parts on the same machine), and what the machine is
#   tests    the tests that only run on CUDA: gsplat's kernels render what our renderer does
#            (values and gradients), a training run with the gsplat render loss, and every
#            renderer / gsplat / training test on this machine
#   bench    one online step of ODG-T and ODG-L at paper resolution (6 x 256 x 704, 8 frames),
#            fp32 and bf16, per stage, and of the shipped odg_cpu checkpoint
#   sweep    speed against error of the shipped checkpoint on this GPU (odg bench --sweep on a
#            one-scene synthetic world): history, pruning, query budgets, bf16/fp16,
#            torch.compile and CUDA graphs
#   presets  the same for ODG-T and ODG-L at paper resolution (random weights: timing only)
#   train    the shipped checkpoint scored on that world on CUDA and on the CPU (the same grid,
#            to float noise), and training speed of odg_cpu and ODG-T with our renderer and
#            with gsplat's
# Everything lands in OUT (default out/gpu), at most a few files per part. DEVICE=cpu runs the
# same commands on the CPU (the CUDA tests skip): how this script is checked without a GPU.
set -uo pipefail
cd "$(dirname "$0")/.."
PART=${1:-all}
OUT=${2:-${OUT:-out/gpu}}
DEVICE=${DEVICE:-cuda}
PY=${PYTHON:-python3}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
export TORCH_EXTENSIONS_DIR="$PWD/.torch_extensions" MAX_JOBS=${MAX_JOBS:-$(nproc)}
failed=0

say() { echo "gpu_checks: $*"; }
step() {  # step NAME command...: run, time, keep going when it fails (each part says so)
    local name=$1 start=$SECONDS
    shift
    say "$name: $*"
    if "$@"; then say "$name: ok in $((SECONDS - start)) s"
    else say "$name: FAILED (exit $?) after $((SECONDS - start)) s"; failed=1; fi
}

# gsplat from the carried wheel where the machine has none (a GPU box may reach no registry)
if ! $PY -c "import gsplat" 2>/dev/null; then
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

part_build() {
    $PY - <<'EOF' > "$OUT/machine.json"
import json, platform, torch
info = {"python": platform.python_version(), "torch": torch.__version__,
        "cuda": torch.version.cuda, "device": None}
if torch.cuda.is_available():
    p = torch.cuda.get_device_properties(0)
    info.update(device=p.name, memory_gib=round(p.total_memory / 2**30, 1),
                capability=f"{p.major}.{p.minor}", multiprocessors=p.multi_processor_count)
try:
    import gsplat
    info["gsplat"] = gsplat.__version__
except ImportError:
    pass
print(json.dumps(info, indent=1))
EOF
    cat "$OUT/machine.json"
    if [ "$DEVICE" = cuda ]; then
        step "gsplat CUDA kernels (JIT)" $PY -c "from gsplat.cuda._backend import _C; assert _C is not None, 'gsplat found no CUDA toolkit'"
    fi
}

part_tests() {
    step "CUDA tests" $PY -m pytest -q -p no:cacheprovider -rs --timeout 900 \
        --junitxml="$OUT/tests.xml" test/test_render_gsplat.py test/test_render.py \
        test/test_loss_render.py test/test_train.py -k "cuda or gsplat or render"
}

part_bench() {
    local runs=out/gpu_bench p k iters=20 warmup=3
    [ "$DEVICE" = cpu ] && iters=1 warmup=0
    rm -rf "$runs"; mkdir -p "$runs"
    for p in odg_t odg_l; do
        for k in fp32 bf16; do
            [ "$DEVICE" = cpu ] && [ "$p" = odg_l ] && continue  # 16 s a step on a CPU
            step "bench $p $k" bash -c "$PY -m odg_ros.cli bench --preset $p --device $DEVICE \
                --precision $k --iters $iters --warmup $warmup --json > $runs/$p-$k.json"
        done
    done
    for k in fp32 bf16; do
        step "bench odg_cpu (shipped) $k" bash -c "$PY -m odg_ros.cli bench --checkpoint \
            model/odg_cpu.pt --device $DEVICE --precision $k --iters $iters --warmup $warmup \
            --json > $runs/odg_cpu_shipped-$k.json"
    done
    $PY -c "import json, sys; json.dump({p.split('/')[-1][:-5]: json.load(open(p))
        for p in sys.argv[1:]}, sys.stdout, indent=1)" "$runs"/*.json > "$OUT/bench.json"
}

WORLD=out/gpu_world  # one 4 s scene (8 keyframes) the training worlds never used
world() {
    [ -f "$WORLD/infos_all.pkl" ] && return
    rm -rf "$WORLD"
    step "one-scene world" $PY -m odg_ros.cli synth --out "$WORLD" --scenes 1 --seconds 4 \
        --seed 1000
    step "infos" $PY -m odg_ros.cli prepare --dataroot "$WORLD" --out "$WORLD/infos_all.pkl" \
        --split all
}

part_sweep() {
    world
    local limit=8 isolate=--no-isolate  # CUDA peak memory is reset per configuration
    [ "$DEVICE" = cpu ] && limit=2 isolate=
    step "sweep of the shipped checkpoint" $PY -m odg_ros.cli bench --sweep \
        --data "$WORLD/infos_all.pkl" --checkpoint model/odg_cpu.pt --device "$DEVICE" \
        --out "$OUT/sweep_shipped" --limit $limit --iters 3 $isolate
}

part_presets() {
    world
    local presets=config/sweep_presets_gpu.json isolate=--no-isolate
    [ "$DEVICE" = cpu ] && presets=config/sweep_presets_gpu_standin.json isolate=
    step "sweep of ODG-T and ODG-L" $PY -m odg_ros.cli bench --sweep --configs "$presets" \
        --data "$WORLD/infos_all.pkl" --checkpoint model/odg_cpu.pt --device "$DEVICE" \
        --out "$OUT/sweep_presets" --limit 2 --iters 3 $isolate
}

part_train() {
    local world=$WORLD runs=out/gpu_runs
    world
    for d in "$DEVICE" cpu; do
        step "eval on $d" bash -c "$PY -m odg_ros.cli eval --checkpoint model/odg_cpu.pt \
            --data '$world/infos_all.pkl' --device $d --json > '$OUT/eval_$d.json'"
        [ "$DEVICE" = cpu ] && break
    done
    local renderers=torch preset
    [ "$DEVICE" = cuda ] && renderers="torch gsplat"
    for preset in odg_cpu odg_t; do
        for r in $renderers; do
            rm -rf "$runs/$preset-$r"
            step "train $preset ($r renderer)" $PY -m odg_ros.cli train --preset "$preset" \
                --data "$world/infos_all.pkl" --out "$runs/$preset-$r" --steps 12 \
                --checkpoint-every 1000 --device "$DEVICE" --renderer "$r" --workers 2
            cp "$runs/$preset-$r/train_log.csv" "$OUT/train_${preset}_$r.csv" 2>/dev/null
        done
        [ "$DEVICE" = cpu ] && break  # ODG-T trains at tens of seconds a step on a CPU
    done
}

case "$PART" in
    build|tests|bench|sweep|presets|train) "part_$PART" ;;
    all) part_build; part_tests; part_train; part_bench; part_sweep; part_presets ;;
    *) say "unknown part '$PART' (build, tests, bench, sweep, presets, train or all)"; exit 2 ;;
esac
say "results in $OUT: $(ls "$OUT" | tr '\n' ' ')"
exit $failed
