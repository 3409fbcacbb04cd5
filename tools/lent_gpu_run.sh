#!/usr/bin/env bash
# One call on a lent GPU machine (16 cores, one H100/H200, no registry), sized to finish in about 9 minutes:
#   1. the attack-step benchmarks of benchmarks/README.md ("GPU plan"), on 2 pinned cores, while
#   2. davis-make-dataset --recipe gen1like renders a Gen1-like dataset on the other 14 cores (time-boxed), then
#   3. davis-train trains an RVT-T victim on it for the time left (a short calibration run sizes --steps), and
#   4. davis-eval-dataset scores it on the held-out test split.
# Everything it prints goes to $OUT/log.txt; the victim's fp16 weights, model card, training log and test scores
# come back under $OUT. Missing packages travel as wheels in .whl/ (pyusb, faster-coco-eval); without hdf5plugin
# there, the dataset is lzf-compressed.
#
# Usage (repository root): bash tools/lent_gpu_run.sh [TOTAL_SECONDS]   (default 540)
# A dry run on a CPU machine:
#   DEVICE=cpu GEN_MIN=0.5 SPLITS=train=20,val=1,test=1 CALIB_STEPS=4 BATCH=2 bash tools/lent_gpu_run.sh 300
set -u
TOTAL=${1:-540}
DEVICE=${DEVICE:-cuda}
CALIB_STEPS=${CALIB_STEPS:-40}
BATCH=${BATCH:-8}
SPLITS=${SPLITS:-train=600,val=12,test=18}
SEQUENCES=$(python3 -c "print(sum(int(p.split('=')[1]) for p in '$SPLITS'.split(',')))")
START=$(date +%s)
OUT=${OUT:-out/lent_gpu}
source tools/lent_gpu_env.sh
NCPU=$(nproc)
PIN_BENCH=""; PIN_GEN=""
if command -v taskset > /dev/null && [ "$NCPU" -ge 8 ]; then
    PIN_BENCH="taskset -c $((NCPU - 2)),$((NCPU - 1))"; PIN_GEN="taskset -c 0-$((NCPU - 3))"
fi
GEN_WORKERS=$(( NCPU > 4 ? NCPU - 2 : 1 ))

# ---- 1 + 2: benchmarks (GPU, 2 cores) beside the dataset (CPU, the other cores)
DATA=/tmp/gen1like
GEN_MIN=${GEN_MIN:-2.8}
say "dataset: $GEN_WORKERS workers, ${GEN_MIN} min"
$PIN_GEN python3 -m davis_rig.cli.make_dataset --out $DATA --recipe gen1like --sequences "$SEQUENCES" \
    --split-sizes "$SPLITS" --seconds 2 --seed 11 --workers "$GEN_WORKERS" --threads 1 \
    --compression lzf --time-budget-min "$GEN_MIN" -q > "$OUT/dataset_summary.json" 2> "$OUT/dataset_stderr.txt" &
GEN_PID=$!

bench() {  # one benchmark command, time-boxed; its output into bench.txt
    local limit=$1; shift
    echo "\$ $*" >> "$OUT/bench.txt"
    timeout "$limit" $PIN_BENCH "$@" >> "$OUT/bench.txt" 2>&1 || echo "(exit $?)" >> "$OUT/bench.txt"
    echo >> "$OUT/bench.txt"
}
say "benchmarks"
bench 60 python3 -m pytest -q -p no:cacheprovider -m gpu tests/attack/test_fixed_step.py
B="python3 benchmarks/attack_step.py --no-cpu --repeats 20 --warmup 5"
bench 40 $B --model base --step attack_loss
bench 40 $B --model base --step cuda_graph
bench 40 $B --model base --step cuda_graph --precision bf16
bench 40 $B --model base --step cuda_graph --clips 4
bench 40 $B --detector davis_rig/assets/detector/rvt_default.safetensors --step cuda_graph
say "benchmarks done"
wait $GEN_PID
say "dataset done (exit $?)"
cat "$OUT/dataset_summary.json" | head -12
tail -3 "$OUT/dataset_stderr.txt"
cp $DATA/dataset_card.json "$OUT/dataset_card.json" 2>/dev/null

# ---- 3: the victim (calibration run sizes the real one)
TRAIN="python3 -m davis_rig.cli.train $DATA --preset tiny --batch $BATCH --seq-len 10 --lr 0.001 --ema 0.999 \
    --seed 0 --device $DEVICE --workers 6 --val-every 0 -q"
CALIB="--out /tmp/calib --steps $CALIB_STEPS --log-every $(( CALIB_STEPS / 4 )) --val-max-sequences 1 --no-export"
say "calibration"
PREC=auto
$TRAIN $CALIB --precision $PREC > /tmp/calib.txt 2>&1 || {
    tail -5 /tmp/calib.txt; PREC=fp32; say "retry fp32"; $TRAIN $CALIB --precision $PREC > /tmp/calib.txt 2>&1 || tail -20 /tmp/calib.txt; }
SPS=$(python3 - <<'EOF'
import json
rows = [json.loads(l) for l in open("/tmp/calib/log.jsonl") if '"elapsed_s"' in l]
rows = [r for r in rows if r.get("kind") == "train"]
print(round((rows[-1]["elapsed_s"] - rows[0]["elapsed_s"]) / (rows[-1]["step"] - rows[0]["step"]), 4))
EOF
)
STEPS=$(python3 -c "print(max(100, int(($(left) - 75) / ${SPS:-0.5})))")
say "calibration: $SPS s/step ($PREC); training $STEPS steps"
$TRAIN --out /tmp/victim --steps "$STEPS" --log-every 50 --val-max-sequences 12 --precision $PREC \
    --time-budget-min $(python3 -c "print(round(($(left) - 45) / 60, 2))") > /tmp/train.txt 2>&1
say "training done (exit $?)"
tail -15 /tmp/train.txt
cp /tmp/victim/log.jsonl "$OUT/train_log.jsonl" 2>/dev/null
cp /tmp/victim/export/model_fp16.safetensors /tmp/victim/export/MODEL_CARD.md "$OUT/" 2>/dev/null || \
python3 - <<'EOF'
# no export (the time budget stopped the run first): the EMA weights of the last checkpoint, fp16
import os, torch
from davis_rig.models.rvt.checkpoint import load_detector, save_safetensors
model = load_detector("/tmp/victim/checkpoints/last.pt")
save_safetensors(model.half(), os.environ["OUT"] + "/model_fp16.safetensors", metadata={"source": "last.pt"})
print("exported last.pt")
EOF

# ---- 4: held-out test split
if [ "$(left)" -gt 15 ] && [ -f "$OUT/model_fp16.safetensors" ]; then
    say "test split"
    timeout $(( $(left) > 20 ? $(left) - 5 : 15 )) python3 -m davis_rig.cli.eval_dataset $DATA \
        --detector "$OUT/model_fp16.safetensors" --device $DEVICE --out "$OUT/test_scores.json" -q | tail -25
fi
say "end"
