#!/usr/bin/env bash
# Collect expert episodes and train on them, in one call on a lent GPU machine (the workplace's `device` tool:
# one H100, 16 cores, no registries reachable, 10 minutes a call), and bring back the epochs' checkpoints.
#
#   bash scripts/device_finetune.sh IDS-FILE [TRAIN-ARGS...]     # e.g. IDS-FILE=runs/device21/ids.txt
#   MODE=dagger bash scripts/device_finetune.sh IDS-FILE --init checkpoints/gsmn [TRAIN-ARGS...]
#
# IDS-FILE holds the train environments to collect, comma-separated, in order (collection stops after COLLECT_S
# seconds, keeping whole episodes only). TRAIN-ARGS are added to `gsmn train supervised` (e.g. --init
# checkpoints/gsmn --train.learning-rate 0.0001 --train.mirror 0.5); training stops after TRAIN_S seconds. With
# MODE=dagger the episodes collected are DAggerFM's expert data D*, its rollouts fly in IDS-FILE's environments
# on WORKERS processes (CPU) and its epochs run on the GPU; a copy is kept after every iteration. Set-up
# as in scripts/device_eval.sh (scripts/device_setup.sh; carry [".whl", ".gl"] and the folder of IDS-FILE).
# Steps, each logged with its time into $OUT/call.log:
#   1. tests/test_training_device.py (its CUDA test runs only there) and the training benchmark
#   2. the 40 dev episodes (data/expert_dev's) and the fresh train episodes, WORKERS processes
#   3. `gsmn train supervised --train.device $DEVICE --train.batch-size 1`, a copy of the checkpoint after
#      every epoch (scripts/keep_iterations.py)
#   4. $OUT/ft_epochs.tgz.partNN (ft_itN: every epoch's or iteration's checkpoint, 1.9 MB each), $OUT/ft_log.jsonl,
#      $OUT/fresh_keys.txt
# Measured (2026-11-27, H100): 17.8 expert episodes/s with 16 workers; 961 training frames/s with the data read.
# Measured (2026-11-28, H200, MODE=dagger, 48 rollouts and M = 192): about 27 s an iteration (rollouts about 11 s).
# CHECKS=0 skips step 1 (saves about a minute of device time); COLLECT_N=N collects only IDS-FILE's first N
# environments (the cap COLLECT_S still applies), e.g. DAggerFM's D*, whose rollouts then fly in all of them.
# The tar is cut into parts of 15 MB (the tool brings back files of at most 16 MiB): ft_epochs.tgz.partNN, rejoined
# with `cat ft_epochs.tgz.part* | tar xz`.
# Here (DEVICE=cpu PY=.venv/bin/python WORKERS=2 and short caps) it runs the same steps, to try it.
set -u
IDS=${1:?usage: device_finetune.sh IDS-FILE [TRAIN-ARGS...]}
shift
OUT=${OUT:-/tmp/out}
COLLECT_S=${COLLECT_S:-150}
TRAIN_S=${TRAIN_S:-270}
DEVICE=${DEVICE:-cuda}
MODE=${MODE:-supervised}
WORKERS=${WORKERS:-16}
CHECKS=${CHECKS:-1}
COLLECT_N=${COLLECT_N:-}
PY=${PY:-python3}
PREFETCH=${PREFETCH:-4}  # threads reading the next episodes while one trains (0: in turn, as before 2026-11-28)
W=${W:-/tmp/device_finetune}
mkdir -p "$OUT" "$W"
L=$OUT/call.log
source scripts/device_log.sh || exit 1

if [ "$CHECKS" != 0 ]; then
    stamp "1. the GPU test"
    timeout -k 10 100 $PY -m pytest -q -p no:cacheprovider -rs tests/test_training_device.py 2>&1 | tail -5 | tee -a "$L"
    stamp "1b. training benchmark (B=1, T=83)"
    timeout -k 10 60 $PY scripts/bench_model.py --kinds gsmn --device "$DEVICE" --batch 1 --steps 83 --repeats 7 \
        --threads 8 2>&1 | tail -2 | tee -a "$L"
fi
collect_ids=$(cat "$IDS")
[ -n "$COLLECT_N" ] && collect_ids=$(echo "$collect_ids" | cut -d, -f1-"$COLLECT_N")

stamp "2. expert episodes: 40 dev, then ${COLLECT_N:-all} environments of $IDS for at most $COLLECT_S s"
$PY -m gsmn.cli collect --out "$W/dev" --split dev --episodes 40 --workers "$WORKERS" 2>&1 | tail -1 | tee -a "$L"
# SIGKILL 40 s after SIGTERM: on the H100 machine collection outlived SIGTERM (whole episodes are kept either way)
timeout -s TERM -k 40 "$COLLECT_S" $PY -m gsmn.cli collect --out "$W/fresh" --env-ids "$collect_ids" \
    --workers "$WORKERS" > "$W/collect.log" 2>&1
tail -c 400 "$W/collect.log" | tr '\r' '\n' | tail -2 | tee -a "$L"
stamp "collected $(ls "$W/fresh" | grep -c 'npz$') episodes, $(du -sh "$W/fresh" | cut -f1)"

stamp "3. $MODE on them ($DEVICE; $*) for $TRAIN_S s"
$PY scripts/keep_iterations.py "$W/ft" --every 2 > "$W/keep.log" 2>&1 &
keep=$!
if [ "$MODE" = dagger ]; then
    train=(train dagger --env-ids "$(cat "$IDS")" --dagger.workers "$WORKERS" --dagger.iterations 1000)
else
    train=(train supervised --kind gsmn --train.epochs 40)
fi
timeout -s TERM -k 30 "$TRAIN_S" $PY -m gsmn.cli "${train[@]}" --data "$W/fresh" --dev "$W/dev" --run "$W/ft" \
    --train.device "$DEVICE" --train.batch-size 1 --train.threads 4 --train.save-every-seconds 60 \
    --train.prefetch "$PREFETCH" "$@" 2>&1 \
    | tr '\r' '\n' | grep -v '%|' | tail -45 | tee -a "$L"
sleep 3
kill "$keep"
stamp "epoch copies: $(ls -d "$W"/ft_it* 2>/dev/null | wc -l)"
cp "$W/ft/log.jsonl" "$OUT/ft_log.jsonl" 2>/dev/null
(cd "$W" && tar czf - ft_it* 2>/dev/null | split -b 15m -d - "$OUT/ft_epochs.tgz.part")
ls "$W/fresh" | grep 'npz$' > "$OUT/fresh_keys.txt"
stamp "done"
exit 0
