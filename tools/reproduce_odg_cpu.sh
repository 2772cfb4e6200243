#!/usr/bin/env bash
# How model/odg_cpu.pt was trained: every command, in order (the worlds of a group of stages
# are made before its first one), on a 2-core CPU (about 60 hours of training steps, ~40 GB of
# synthetic worlds under data/, checkpoints under runs/). Each numbered stage is one row of
# model/CHANGELOG.md; stage N's int8 file is runs/odg_cpu_stage<N>.pt. Stages marked "not
# shipped" record a run that was tried and not kept; stopped ones were stopped by hand at the
# checkpoint named, which a plain run of this file does not do (it trains their whole schedule).
# CPU training is not bit-reproducible across machines and thread counts; the worlds are
# (odg synth writes the same bytes for the same seed, test/data/test_synth.py pins them).
#
#   bash tools/reproduce_odg_cpu.sh            # from the repository root, in the .venv
set -euo pipefail
cd "$(dirname "$0")/.."

odg synth --out data/synth24 --scenes 24 --seconds 8 --seed 1
odg prepare --dataroot data/synth24 --out data/synth24/infos_train.pkl --split train
odg prepare --dataroot data/synth24 --out data/synth24/infos_val.pkl --split val
COMMON="--data data/synth24/infos_train.pkl --epochs 1000 --lr 4e-4 --backbone-lr-mult 1.0 \
    --workers 0 --no-history-grad --render-pixels 256 --checkpoint-every 200"
K32='--set points_per_layer=[1,2,4,8,16,32] --set num_dynamic=50'
# the options of every stage on several worlds, from (5) on
WORLD_OPTS="--epochs 1000 --lr 3e-4 --backbone-lr-mult 1.0 --workers 1 --no-history-grad \
    --render-pixels 256"
worlds() {  # SEED...: a 24-scene world data/synth24s<SEED> each, then their infos (all scenes)
    local seed
    for seed in "$@"; do
        odg synth --out "data/synth24s$seed" --scenes 24 --seconds 8 --seed "$seed"
    done
    for seed in "$@"; do
        odg prepare --dataroot "data/synth24s$seed" --out "data/synth24s$seed/infos_all.pkl" \
            --split all
    done
}
infos_of() {  # SEED...: seed 1's train split and every scene of the worlds of the seeds
    local seed
    echo data/synth24/infos_train.pkl
    for seed in "$@"; do echo "data/synth24s$seed/infos_all.pkl"; done
}
export_int8() {  # CHECKPOINT OUT: the int8 export every stage ships, calibrated on seed 1's train
    odg export --checkpoint "$1" --out "$2" --compress int8 \
        --calibrate data/synth24/infos_train.pkl --limit 48
}
one_process_stage() {  # OUT INIT STEPS "SEED..." [OPTION...]: one process on infos_of the seeds
    local out=$1 init=$2 steps=$3 seeds=$4
    shift 4
    odg train --preset odg_cpu --data $(infos_of $seeds) $WORLD_OPTS --checkpoint-every 200 \
        --out "$out" --init "$init" --steps "$steps" --warmup 100 "$@"
}
stage() {  # N FROM OUT STEPS "SEED..." [OPTION...]: stage N, two processes (torchrun, DDP on
    # gloo, batch 2) on infos_of the seeds from stage FROM's file, exported to
    # runs/odg_cpu_stage<N>.pt
    local n=$1 from=$2 out=$3 steps=$4 seeds=$5
    shift 5
    OMP_NUM_THREADS=1 torchrun --standalone --nproc_per_node 2 -m odg_ros.commands train \
        --preset odg_cpu --data $(infos_of $seeds) $WORLD_OPTS --checkpoint-every 100 \
        --out "$out" --init "runs/odg_cpu_stage$from.pt" --steps "$steps" --warmup 50 "$@"
    export_int8 "$out/final.pt" "runs/odg_cpu_stage$n.pt"
}
# (1) 3,800 steps at K = 32 (the earlier preset)
odg train --preset odg_cpu $K32 $COMMON --out runs/cpu24 --steps 3800 --warmup 200
# (2) a 20,000-step schedule from (1), stopped once runs/cpu24b/latest.pt holds step 1,800
odg train --preset odg_cpu $K32 $COMMON --out runs/cpu24b --init runs/cpu24/final.pt \
    --steps 20000 --warmup 100
# (3) K = 128: --init grows the last point head from 32 to 128 points
odg train --preset odg_cpu --set num_dynamic=50 $COMMON --out runs/cpu24w \
    --init runs/cpu24b/latest.pt --steps 3800 --warmup 100
# (4) the shipped preset (100 dynamic queries): --init keeps the 50 trained ones, adds 50
odg train --preset odg_cpu $COMMON --out runs/cpu24d100f --init runs/cpu24w/final.pt \
    --steps 3200 --warmup 100
# (5) more data: two more worlds, every one of their scenes for training (seed 1's val held
# out); in-process data loading
# (6) still more data: seeds 4 and 5, every scene for training
# (7) seeds 6 and 7 as well, every scene for training
# (8) seeds 8 and 9 as well (a stopped run continues with the same command plus --resume)
worlds 2 3 4 5 6 7 8 9
one_process_stage runs/cpu66 runs/cpu24d100f/final.pt 3000 "2 3" --workers 0
one_process_stage runs/cpu114 runs/cpu66/final.pt 2500 "2 3 4 5"
one_process_stage runs/cpu162 runs/cpu114/final.pt 2600 "2 3 4 5 6 7"
one_process_stage runs/cpu210 runs/cpu162/final.pt 3400 "2 3 4 5 6 7 8 9"
export_int8 runs/cpu210/final.pt runs/odg_cpu_stage8.pt
# (9) a new machine: seed 1, seed 2 and two new worlds, seeds 10 and 11, from the (8) file;
# the 2,100-step schedule was stopped at its step-1,800 checkpoint (runs/cpu90/latest.pt)
worlds 10 11
one_process_stage runs/cpu90 runs/odg_cpu_stage8.pt 2100 "2 10 11"
export_int8 runs/cpu90/latest.pt runs/odg_cpu_stage9.pt
# From (10) on every stage runs two processes of one thread each from the file of the stage
# named, and ships its int8 export. Stopped runs continued with the same command plus --resume
# from their last checkpoint: (12) after step 917, (15) after 666 (from 600), (16) after
# ~1,240 (from 1,200), (21) after 141 (from 100), (22) after 766 (from 700), (25) after 901
# (from 900), (27) after 147 (from 100), (29) after 154 (from 100), (31) after ~190 (from
# 100), (34) after 929 (from 900), (37) after 451 (from 400: the same run, bit for bit).
# (10) the same 90 scenes, from the (9) file
stage 10 9 runs/cpu90b_ddp 1500 "2 10 11"
# (11) two more worlds, seeds 12 and 13; 138 scenes, from the (10) file
# (12) two more worlds, seeds 14 and 15; 186 scenes, from the (11) file
# (13) a second pass over the same 186 scenes, in another order, from the (12) file
# (14), not shipped: a third pass, the (13) command with --out runs/cpu186c
# --init runs/odg_cpu_stage13.pt --steps 1500 --seed 2, exported to runs/odg_cpu_stage14.pt
# (15) two more worlds, seeds 16 and 17; 234 scenes, from the (13) file
# (16) a second pass over the 234 scenes, in another order, from the (15) file: shipped
worlds 12 13 14 15 16 17
stage 11 10 runs/cpu138 1500 "2 10 11 12 13"
stage 12 11 runs/cpu186 1500 "2 10 11 12 13 14 15"
stage 13 12 runs/cpu186b 1200 "2 10 11 12 13 14 15" --seed 1
stage 15 13 runs/cpu234 1500 "2 10 11 12 13 14 15 16 17"
stage 16 15 runs/cpu234b 1500 "2 10 11 12 13 14 15 16 17" --seed 1
odg eval --checkpoint runs/odg_cpu_stage16.pt --data data/synth24/infos_val.pkl
# the second held-out world, made after training
odg synth --out data/synth8s18 --scenes 8 --seconds 8 --seed 18
odg prepare --dataroot data/synth8s18 --out data/synth8s18/infos_all.pkl --split all
odg eval --checkpoint runs/odg_cpu_stage16.pt --data data/synth8s18/infos_all.pkl
# (17), not shipped: seed 1 and three new worlds (19, 20, 21), from the (16) file
# (18), not shipped alone ((19) starts from it): five of the earlier worlds regenerated
# (seeds 2, 10-13, the commands of (5), (9) and (11) above) and added to (17)'s set,
# from the (16) file
# (19), shipped until (20) (which starts from it): seeds 14 and 15 regenerated ((12)'s
# commands) and added to (18)'s set, from the (18) file
# (20), shipped until (21) (which starts from it): seeds 16 and 17 regenerated ((15)'s
# commands) and added to (19)'s set, all 306 scenes, from the (19) file
# (21), shipped until (22) (which starts from it): a second pass over the 306 scenes in another
# order, from the (20) file
worlds 19 20 21
stage 17 16 runs/cpu90n 1000 "19 20 21"
stage 18 16 runs/cpu210 1100 "2 10 11 12 13 19 20 21"
stage 19 18 runs/cpu258 1500 "2 10 11 12 13 14 15 19 20 21"
seeds="2 10 11 12 13 14 15 16 17 19 20 21"
stage 20 19 runs/cpu306 1300 "$seeds"
stage 21 20 runs/cpu306b 1500 "$seeds" --seed 1
# (22) to (37) in pairs: stage N adds two new worlds, seeds N and N + 1, to the scenes of
# stage N - 1 (seed 1's 18 training scenes and 24 a world) and trains on them from its file;
# stage N + 1 is a second pass over the same scenes in another order, from stage N's file.
# Shipped: (22) until (23), (23) until (24), (24) until (25), (25) until (27), (27) until
# (28), (28) until (29), (29) until (31), (31) until (33), (33) until (35), (35) until (37),
# and (37). (26), (30), (32), (34) and (36) were not shipped alone (their second pass starts
# from them).
for n in 22 24 26 28 30 32 34 36; do
    worlds $n $((n + 1))
    seeds="$seeds $n $((n + 1))"
    scenes=$((18 + 24 * $(wc -w <<< "$seeds")))
    steps=1200; [ $n = 22 ] && steps=1500
    stage $n $((n - 1)) "runs/cpu$scenes" $steps "$seeds"
    stage $((n + 1)) $n "runs/cpu${scenes}b" 1200 "$seeds" --seed 1
done
# (38), shipped: the query-budget heads trained on top of (37), every other weight frozen
# (docs/query_budget.md); the worlds of every scene class, none of them a held-out seed
odg synth --out data/synth8s2 --scenes 8 --seconds 8 --seed 2
odg prepare --dataroot data/synth8s2 --out data/synth8s2/infos_train.pkl --split train
for spec in "open-road 31 normal 3" "city-quiet 32 quiet 3" "city-dense 33 dense 3" \
        "open-road 34 quiet 3" "city-normal 41 normal 4" "open-road 42 dense 4" \
        "city-quiet 43 quiet 4" "city-dense 44 dense 4" "open-road 45 normal 4" \
        "city-normal 46 normal 4"; do
    set -- $spec
    roads=city; [ "$1" = open-road ] && roads=open-road
    odg synth --out "data/budget/$1-$2" --scenes "$4" --seconds 4 --seed "$2" --traffic "$3" \
        --roads "$roads"
    odg prepare --dataroot "data/budget/$1-$2" --out "data/budget/$1-$2/infos_all.pkl" --split all
done
OMP_NUM_THREADS=1 odg train --budget-heads --init runs/odg_cpu_stage37.pt \
    --data data/synth8s2/infos_train.pkl data/budget/*/infos_all.pkl \
    --out runs/budget --skip-epochs 12
cp runs/budget/budget_heads.pt model/odg_cpu.pt
# (39), shipped: (38) with its calibration, fitted on small worlds of training seeds
odg synth --out data/calib/open-road-31 --scenes 3 --seconds 4 --seed 31 --roads open-road
odg synth --out data/calib/city-quiet-32 --scenes 3 --seconds 4 --seed 32 --traffic quiet
odg synth --out data/calib/city-dense-33 --scenes 3 --seconds 4 --seed 33 --traffic dense
odg synth --out data/calib/city-normal-41 --scenes 4 --seconds 4 --seed 41
for world in data/calib/*; do
    odg prepare --dataroot "$world" --out "$world/infos_all.pkl" --split all
done
mv model/odg_cpu.pt runs/odg_cpu_stage38.pt
odg export --checkpoint runs/odg_cpu_stage38.pt --out model/odg_cpu.pt --keep-thresholds \
    --calibrate data/calib/open-road-31/infos_all.pkl data/calib/city-quiet-32/infos_all.pkl \
    data/calib/city-dense-33/infos_all.pkl data/calib/city-normal-41/infos_all.pkl
# the shipped file, (39) (its labels are (37)'s):
odg eval --checkpoint model/odg_cpu.pt --data data/synth24/infos_val.pkl
odg eval --checkpoint model/odg_cpu.pt --data data/synth8s18/infos_all.pkl
