#!/usr/bin/env bash
# The planted-blind-spot control at a GPU budget, in one call on a lent GPU machine (16 cores, one H100/H200, no
# registry), sized to finish in about 9.5 minutes:
#   1. two victims are planted side by side from the bundled RVT-T with the legs trigger (legs white, the rest
#      black): A trains the detection head alone (backbone frozen), B the last backbone stage too;
#      meanwhile a 10-step davis-attack run checks that --detector-step cuda_graph works on this machine;
#   2. the victim whose probe separates best (random grids still detected at a mean top score >= 0.7 and the
#      trigger lowest; else the largest gap random - trigger) is attacked by the paper's recipe from three seeds
#      at once, without knowledge of the trigger, each stopped (SIGTERM: checkpoint, best texture kept) before the
#      time runs out.
# Everything it prints goes to $OUT/log.txt; the run folders (both victims' weights, probes, logs and textures; the
# recoveries' checkpoints/last.pt, so that `davis-attack optimize --resume` continues them on another machine; not
# the victims' training state) come back as results.tgz in parts of 15 MiB: cat results.tgz.part_* | tar xz.
#
# Usage (repository root): bash tools/lent_gpu_planted.sh [TOTAL_SECONDS]   (default 560)
# A dry run on a CPU machine:
#   DEVICE=cpu PLANT_S=20 PLANT_STEPS=4 POOL=8 PROBE=3 ITER_EAGER=4 VAL=4 RECOVER_POOL=8 bash tools/lent_gpu_planted.sh 240
set -u
TOTAL=${1:-560}
DEVICE=${DEVICE:-cuda}
PLANT_S=${PLANT_S:-170}          # fine-tuning seconds of each victim
PLANT_STEPS=${PLANT_STEPS:-20000} # an upper bound: PLANT_S stops the planting first
POOL=${POOL:-48}                  # pre-rasterized clips of each victim's pool
PROBE=${PROBE:-12}                # held-out probe clips
ITER_GRAPH=${ITER_GRAPH:-1500}    # recovery steps (the alpha schedule runs over these) with the CUDA graph step,
ITER_EAGER=${ITER_EAGER:-700}     # and with the eager one (about 3x slower)
VAL=${VAL:-64}                    # recovery validation clips
RECOVER_POOL=${RECOVER_POOL:-32}
START=$(date +%s)
OUT=${OUT:-out/lent_gpu_planted}
W=${WORK:-/tmp/planted}
mkdir -p "$W"
source tools/lent_gpu_env.sh

# ---- 1: two victims side by side, and the cuda_graph check
PLANT="python3 tools/make_trigger_victim.py --trigger-white-parts legs --steps $PLANT_STEPS --clips-per-step 8 \
    --pool-size $POOL --refresh-every 150 --probe-clips $PROBE --save-every 1000000 --time-limit $PLANT_S \
    --device $DEVICE --threads 4 --seed 0"
say "planting A (head only, lr 1e-3) and B (last stage + head, lr 5e-4) for ${PLANT_S} s each"
$PLANT --out $W/victim_A --train-from-stage 4 --lr 1e-3 > $W/victim_A.log 2>&1 &
PID_A=$!
$PLANT --out $W/victim_B --train-from-stage 3 --lr 5e-4 > $W/victim_B.log 2>&1 &
PID_B=$!
STEP_MODE=eager
ITER=$ITER_EAGER
if [ "$DEVICE" != cpu ]; then
    timeout 120 python3 -m davis_rig.cli.attack optimize --out $W/graph_check --cells 10 --iterations 10 \
        --clips-per-step 8 --pool-size 8 --val-clips 8 --validate-every 10 --detector-step cuda_graph \
        --device $DEVICE --threads 2 -q > $W/graph_check.log 2>&1 && { STEP_MODE=cuda_graph; ITER=$ITER_GRAPH; }
    say "cuda_graph check: detector step $STEP_MODE"; tail -3 $W/graph_check.log
fi
wait $PID_A; say "victim A done (exit $?)"; grep -E "^step" $W/victim_A.log | tail -2
wait $PID_B; say "victim B done (exit $?)"; grep -E "^step" $W/victim_B.log | tail -2

VICTIM=$(python3 - "$W" <<'EOF'
import json, sys
from pathlib import Path
rows = []
for name in ("victim_A", "victim_B"):
    p = Path(sys.argv[1]) / name / "summary.json"
    if not p.is_file():
        print(f"{name}: no summary", file=sys.stderr)
        continue
    s = json.loads(p.read_text())["after"]
    t, r = s["trigger"]["mean_top_score"], s["random (mean)"]["mean_top_score"]
    print(f"{name}: trigger {t:.3f} (SeqASR {s['trigger']['SeqASR']:.2f}), random mean {r:.3f}, lowest "
          f"{s['random (lowest top score)']:.3f}, white {s['white']['mean_top_score']:.3f}, black "
          f"{s['black']['mean_top_score']:.3f}, 20% flipped {s['trigger, 20% flipped']['mean_top_score']:.3f}",
          file=sys.stderr)
    rows.append((r >= 0.7, t if r >= 0.7 else t - r, name))
# selective ones first, then the lowest trigger score (selective) or the largest gap random - trigger
print(sorted(rows, key=lambda row: (not row[0], row[1]))[0][2] if rows else "")
EOF
)
say "recovering the trigger of ${VICTIM:-nothing}: $ITER steps, detector step $STEP_MODE"
[ -n "$VICTIM" ] || exit 1

# ---- 2: three seeds of the paper's recipe at once, stopped in time
STOP_AFTER=$(( $(left) - 40 ))
PIDS=""
for SEED in 0 1 2; do
    timeout -s TERM -k 20 $STOP_AFTER python3 -m davis_rig.cli.attack optimize --out $W/recover_$SEED --cells 10 \
        --loss top --lr 1e-2 --iterations $ITER --clips-per-step 8 --pool-size $RECOVER_POOL --refresh-every 100 \
        --validate-every 250 --val-clips $VAL --detector $W/$VICTIM/model.safetensors --detector-step $STEP_MODE \
        --device $DEVICE --threads 4 --seed $SEED -q > $W/recover_$SEED.log 2>&1 &
    PIDS="$PIDS $!"
done
wait $PIDS  # (a bare wait would also wait for the tee of the log)
say "recoveries done"
for SEED in 0 1 2; do
    echo "seed $SEED: $(grep -c '"loss"' $W/recover_$SEED/log.jsonl 2>/dev/null) steps; $(cat $W/recover_$SEED/best.json 2>/dev/null | head -c 400)"
    tail -2 $W/recover_$SEED.log
done

# ---- what comes back
echo "$VICTIM" > $W/chosen_victim.txt
find $W -name "*.pt" ! -path "$W/recover_*/checkpoints/*" -delete  # the recoveries' run state is small
tar czf /tmp/results.tgz -C "$(dirname $W)" "$(basename $W)"
split -b 15M /tmp/results.tgz "$OUT/results.tgz.part_"
ls -la "$OUT"
say "end"
