#!/usr/bin/env bash
# How model/odg_cpu.pt was trained: every command, in order, on a 2-core CPU (about 60 hours of
# training steps, ~40 GB of synthetic worlds under data/, checkpoints under runs/). Each
# numbered block is one row of model/CHANGELOG.md. Blocks marked "not shipped" record a run
# that was tried and not kept; blocks "stopped at step N" were stopped by hand at that step's
# checkpoint, which a plain run of this file does not do (it trains their whole schedule).
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
# the options of every two-process (torchrun) stage
DDP_OPTS="--epochs 1000 --lr 3e-4 --backbone-lr-mult 1.0 --workers 1 --no-history-grad \
    --render-pixels 256 --checkpoint-every 100"
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
ddp_stage() {  # OUT INIT STEPS "SEED..." [OPTION...]: a two-process (torchrun) stage on seed
    # 1's train split and the worlds of the seeds, from the checkpoint INIT
    local out=$1 init=$2 steps=$3 seed data=(data/synth24/infos_train.pkl)
    for seed in $4; do data+=("data/synth24s$seed/infos_all.pkl"); done
    shift 4
    OMP_NUM_THREADS=1 torchrun --standalone --nproc_per_node 2 -m odg_ros.commands train \
        --preset odg_cpu --data "${data[@]}" $DDP_OPTS --out "$out" --init "$init" \
        --steps "$steps" --warmup 50 "$@"
}
export_int8() {  # CHECKPOINT OUT: the int8 export every stage ships, calibrated on seed 1's train
    odg export --checkpoint "$1" --out "$2" --compress int8 \
        --calibrate data/synth24/infos_train.pkl --limit 48
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
# (5) more data: two more worlds, every one of their scenes for training (seed 1's val held out)
worlds 2 3
odg train --preset odg_cpu --data data/synth24/infos_train.pkl data/synth24s2/infos_all.pkl \
    data/synth24s3/infos_all.pkl --epochs 1000 --lr 3e-4 --backbone-lr-mult 1.0 --workers 0 \
    --no-history-grad --render-pixels 256 --checkpoint-every 200 --out runs/cpu66 \
    --init runs/cpu24d100f/final.pt --steps 3000 --warmup 100
# (6) still more data: seeds 4 and 5, every scene for training
worlds 4 5
odg train --preset odg_cpu --data data/synth24/infos_train.pkl data/synth24s2/infos_all.pkl \
    data/synth24s3/infos_all.pkl data/synth24s4/infos_all.pkl data/synth24s5/infos_all.pkl \
    --epochs 1000 --lr 3e-4 --backbone-lr-mult 1.0 --workers 1 --no-history-grad \
    --render-pixels 256 --checkpoint-every 200 --out runs/cpu114 --init runs/cpu66/final.pt \
    --steps 2500 --warmup 100
# (7) seeds 6 and 7 as well, every scene for training
worlds 6 7
odg train --preset odg_cpu --data data/synth24/infos_train.pkl \
    data/synth24s{2,3,4,5,6,7}/infos_all.pkl \
    --epochs 1000 --lr 3e-4 --backbone-lr-mult 1.0 --workers 1 --no-history-grad \
    --render-pixels 256 --checkpoint-every 200 --out runs/cpu162 --init runs/cpu114/final.pt \
    --steps 2600 --warmup 100
# (8) seeds 8 and 9 as well (a stopped run continues with the same command plus --resume)
worlds 8 9
odg train --preset odg_cpu --data data/synth24/infos_train.pkl \
    data/synth24s{2,3,4,5,6,7,8,9}/infos_all.pkl \
    --epochs 1000 --lr 3e-4 --backbone-lr-mult 1.0 --workers 1 --no-history-grad \
    --render-pixels 256 --checkpoint-every 200 --out runs/cpu210 --init runs/cpu162/final.pt \
    --steps 3400 --warmup 100
export_int8 runs/cpu210/final.pt runs/odg_cpu_stage8.pt
# (9) a new machine: seed 1, seed 2 and two new worlds, seeds 10 and 11, from the (8) file
#;
# the 2,100-step schedule was stopped at its step-1,800 checkpoint (runs/cpu90/latest.pt)
worlds 10 11
odg train --preset odg_cpu --data data/synth24/infos_train.pkl \
    data/synth24s{2,10,11}/infos_all.pkl \
    --epochs 1000 --lr 3e-4 --backbone-lr-mult 1.0 --workers 1 --no-history-grad \
    --render-pixels 256 --checkpoint-every 200 --out runs/cpu90 --init runs/odg_cpu_stage8.pt \
    --steps 2100 --warmup 100
export_int8 runs/cpu90/latest.pt runs/odg_cpu_stage9.pt
# (10) the same 90 scenes, two processes of one thread each (DDP on gloo, batch 2), from the
# (9) file
ddp_stage runs/cpu90b_ddp runs/odg_cpu_stage9.pt 1500 "2 10 11"
export_int8 runs/cpu90b_ddp/final.pt runs/odg_cpu_stage10.pt
# (11) two more worlds, seeds 12 and 13; 138 scenes, from the (10) file
worlds 12 13
ddp_stage runs/cpu138 runs/odg_cpu_stage10.pt 1500 "2 10 11 12 13"
export_int8 runs/cpu138/final.pt runs/odg_cpu_stage11.pt
# (12) two more worlds, seeds 14 and 15; 186 scenes, from the (11) file; stopped at step 917, continued with the same command
# plus --resume
worlds 14 15
ddp_stage runs/cpu186 runs/odg_cpu_stage11.pt 1500 "2 10 11 12 13 14 15"
export_int8 runs/cpu186/final.pt runs/odg_cpu_stage12.pt
# (13) a second pass over the same 186 scenes, in another order, from the (12) file
#
ddp_stage runs/cpu186b runs/odg_cpu_stage12.pt 1200 "2 10 11 12 13 14 15" --seed 1
export_int8 runs/cpu186b/final.pt runs/odg_cpu_stage13.pt
# (14), not shipped: a third pass, the (13) command with --out runs/cpu186c
# --init runs/odg_cpu_stage13.pt --steps 1500 --seed 2, exported to runs/odg_cpu_stage14.pt
# (15) two more worlds, seeds 16 and 17; 234 scenes, from the (13) file; stopped after step 666, continued with the same command
# plus --resume (from the step-600 checkpoint)
worlds 16 17
ddp_stage runs/cpu234 runs/odg_cpu_stage13.pt 1500 "2 10 11 12 13 14 15 16 17"
export_int8 runs/cpu234/final.pt runs/odg_cpu_stage15.pt
# (16) a second pass over the 234 scenes, in another order, from the (15) file; stopped after step ~1,240, continued with the same
# command plus --resume (from the step-1,200 checkpoint)
ddp_stage runs/cpu234b runs/odg_cpu_stage15.pt 1500 "2 10 11 12 13 14 15 16 17" --seed 1
export_int8 runs/cpu234b/final.pt model/odg_cpu.pt
odg eval --checkpoint model/odg_cpu.pt --data data/synth24/infos_val.pkl
# the second held-out world, made after training
odg synth --out data/synth8s18 --scenes 8 --seconds 8 --seed 18
odg prepare --dataroot data/synth8s18 --out data/synth8s18/infos_all.pkl --split all
odg eval --checkpoint model/odg_cpu.pt --data data/synth8s18/infos_all.pkl
# (17), not shipped: seed 1 and three new worlds (19, 20, 21), from the (16) file
worlds 19 20 21
ddp_stage runs/cpu90n runs/odg_cpu_stage16.pt 1000 "19 20 21"
export_int8 runs/cpu90n/final.pt runs/odg_cpu_stage17.pt
# (18), not shipped alone ((19) starts from it): five of the earlier worlds regenerated
# (seeds 2, 10-13, the commands of (5), (9) and (11) above) and added to (17)'s set,
# from the (16) file
ddp_stage runs/cpu210 runs/odg_cpu_stage16.pt 1100 "2 10 11 12 13 19 20 21"
export_int8 runs/cpu210/final.pt runs/odg_cpu_stage18.pt
# (19), shipped until (20) (which starts from it): seeds 14 and 15 regenerated ((12)'s
# commands) and added to (18)'s set, from the (18) file
ddp_stage runs/cpu258 runs/odg_cpu_stage18.pt 1500 "2 10 11 12 13 14 15 19 20 21"
export_int8 runs/cpu258/final.pt runs/odg_cpu_stage19.pt
# (20), shipped until (21) (which starts from it): seeds 16 and 17 regenerated ((15)'s
# commands) and added to (19)'s set, all 306 scenes, from the (19) file
ddp_stage runs/cpu306 runs/odg_cpu_stage19.pt 1300 "2 10 11 12 13 14 15 16 17 19 20 21"
export_int8 runs/cpu306/final.pt runs/odg_cpu_stage20.pt
# (21), shipped until (22) (which starts from it): a second pass over the 306 scenes in another
# order, from the (20) file; stopped after
# step 141, continued with the same command plus --resume (from the step-100 checkpoint)
ddp_stage runs/cpu306b runs/odg_cpu_stage20.pt 1500 "2 10 11 12 13 14 15 16 17 19 20 21" --seed 1
export_int8 runs/cpu306b/final.pt runs/odg_cpu_stage21.pt
# (22), shipped until (23) (which starts from it): two new worlds, seeds 22 and 23, and the 306
# scenes, from the (21) file; stopped after
# step 766, continued with the same command plus --resume (from the step-700 checkpoint)
worlds 22 23
ddp_stage runs/cpu354 runs/odg_cpu_stage21.pt 1500 "2 10 11 12 13 14 15 16 17 19 20 21 22 23"
export_int8 runs/cpu354/final.pt runs/odg_cpu_stage22.pt
# (23), shipped until (24) (which starts from it): a second pass over the 354 scenes in another
# order, from the (22) file
ddp_stage runs/cpu354b runs/odg_cpu_stage22.pt 1200 "2 10 11 12 13 14 15 16 17 19 20 21 22 23" --seed 1
export_int8 runs/cpu354b/final.pt runs/odg_cpu_stage23.pt
# (24), shipped until (25) (which starts from it): two new worlds, seeds 24 and 25, and the 354
# scenes, from the (23) file
worlds 24 25
ddp_stage runs/cpu402 runs/odg_cpu_stage23.pt 1200 "2 10 11 12 13 14 15 16 17 19 20 21 22 23 24 25"
export_int8 runs/cpu402/final.pt runs/odg_cpu_stage24.pt
# (25), shipped until (27): a second pass over the 402 scenes in another order, from the
# (24) file
#; stopped after step 901, continued with the same
# command plus --resume (from the step-900 checkpoint)
ddp_stage runs/cpu402b runs/odg_cpu_stage24.pt 1200 "2 10 11 12 13 14 15 16 17 19 20 21 22 23 24 25" --seed 1
export_int8 runs/cpu402b/final.pt runs/odg_cpu_stage25.pt
# (26), not shipped alone (the second pass, (27), starts from it): two new worlds, seeds 26 and
# 27, and the 402 scenes, from the (25) file (the export above)
worlds 26 27
ddp_stage runs/cpu450 runs/odg_cpu_stage25.pt 1200 "2 10 11 12 13 14 15 16 17 19 20 21 22 23 24 25 26 27"
export_int8 runs/cpu450/final.pt runs/odg_cpu_stage26.pt
# (27), shipped until (28): a second pass over the 450 scenes in another order, from the (26) file;
# stopped after step 147, continued with the same command plus --resume (from the step-100
# checkpoint)
ddp_stage runs/cpu450b runs/odg_cpu_stage26.pt 1200 "2 10 11 12 13 14 15 16 17 19 20 21 22 23 24 25 26 27" --seed 1
export_int8 runs/cpu450b/final.pt runs/odg_cpu_stage27.pt
# (28), shipped until (29): two new worlds, seeds 28 and 29, and the 450 scenes, from the (27) file
# (the export above)
worlds 28 29
ddp_stage runs/cpu498 runs/odg_cpu_stage27.pt 1200 "2 10 11 12 13 14 15 16 17 19 20 21 22 23 24 25 26 27 28 29"
export_int8 runs/cpu498/final.pt runs/odg_cpu_stage28.pt
# (29), shipped until (31): a second pass over the 498 scenes in another order, from the (28) file
# (the export above);
# stopped after step 154, continued with the same command plus --resume (from the step-100
# checkpoint)
ddp_stage runs/cpu498b runs/odg_cpu_stage28.pt 1200 "2 10 11 12 13 14 15 16 17 19 20 21 22 23 24 25 26 27 28 29" --seed 1
export_int8 runs/cpu498b/final.pt runs/odg_cpu_stage29.pt
# (30), not shipped alone (the second pass, (31), starts from it): two new worlds, seeds 30 and
# 31, and the 498 scenes, from the (29) file (the export above)
worlds 30 31
ddp_stage runs/cpu546 runs/odg_cpu_stage29.pt 1200 "2 10 11 12 13 14 15 16 17 19 20 21 22 23 24 25 26 27 28 29 30 31"
export_int8 runs/cpu546/final.pt runs/odg_cpu_stage30.pt
# (31), shipped until (33): a second pass over the 546 scenes in another order, from the (30) file;
# stopped after step ~190, continued with the same command plus --resume (from the step-100
# checkpoint)
ddp_stage runs/cpu546b runs/odg_cpu_stage30.pt 1200 "2 10 11 12 13 14 15 16 17 19 20 21 22 23 24 25 26 27 28 29 30 31" --seed 1
export_int8 runs/cpu546b/final.pt runs/odg_cpu_stage31.pt
# (32), not shipped alone (the second pass, (33), starts from it): two new worlds, seeds 32 and
# 33, and the 546 scenes, from the (31) file (the export above)
worlds 32 33
ddp_stage runs/cpu594 runs/odg_cpu_stage31.pt 1200 "2 10 11 12 13 14 15 16 17 19 20 21 22 23 24 25 26 27 28 29 30 31 32 33"
export_int8 runs/cpu594/final.pt runs/odg_cpu_stage32.pt
# (33), shipped until (35): a second pass over the 594 scenes in another order, from the (32) file
ddp_stage runs/cpu594b runs/odg_cpu_stage32.pt 1200 "2 10 11 12 13 14 15 16 17 19 20 21 22 23 24 25 26 27 28 29 30 31 32 33" --seed 1
export_int8 runs/cpu594b/final.pt runs/odg_cpu_stage33.pt
# (34), not shipped alone (the second pass, (35), starts from it): two new worlds, seeds 34 and
# 35, and the 594 scenes, from the (33) file (the export above); stopped after step 929,
# continued with the same command plus --resume (from the step-900 checkpoint)
worlds 34 35
ddp_stage runs/cpu642 runs/odg_cpu_stage33.pt 1200 "2 10 11 12 13 14 15 16 17 19 20 21 22 23 24 25 26 27 28 29 30 31 32 33 34 35"
export_int8 runs/cpu642/final.pt runs/odg_cpu_stage34.pt
# (35), shipped until (37): a second pass over the 642 scenes in another order, from the (34) file
ddp_stage runs/cpu642b runs/odg_cpu_stage34.pt 1200 "2 10 11 12 13 14 15 16 17 19 20 21 22 23 24 25 26 27 28 29 30 31 32 33 34 35" --seed 1
export_int8 runs/cpu642b/final.pt runs/odg_cpu_stage35.pt
# (36), not shipped alone (the second pass, (37), starts from it): two new worlds, seeds 36 and
# 37, and the 642 scenes, from the (35) file (the export above)
worlds 36 37
ddp_stage runs/cpu690 runs/odg_cpu_stage35.pt 1200 "2 10 11 12 13 14 15 16 17 19 20 21 22 23 24 25 26 27 28 29 30 31 32 33 34 35 36 37"
export_int8 runs/cpu690/final.pt runs/odg_cpu_stage36.pt
# (37), shipped: a second pass over the 690 scenes in another order, from the (36) file
# (stopped after step 451, continued with the same command plus --resume from the step-400
# checkpoint: the same run, bit for bit)
ddp_stage runs/cpu690b runs/odg_cpu_stage36.pt 1200 "2 10 11 12 13 14 15 16 17 19 20 21 22 23 24 25 26 27 28 29 30 31 32 33 34 35 36 37" --seed 1
export_int8 runs/cpu690b/final.pt model/odg_cpu.pt
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
mv model/odg_cpu.pt runs/odg_cpu_stage37.pt
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
