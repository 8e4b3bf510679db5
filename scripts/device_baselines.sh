#!/usr/bin/env bash
# The baselines' retraining of runs/plan24.md (docs/training.md, "The baselines with GSMN's supervised budget") in
# one call on a lent GPU machine (the workplace's `device` tool: 16 cores, one GPU, 10 minutes a call):
#
#   bash scripts/device_baselines.sh        # carry [".whl", ".gl", "runs/gs-fpv-mem_sup16", "runs/gs-fpv_sup16"]
#
# 1. expert data, WORKERS processes: data/expert_train (the first 600 train environments, as here), data/expert_dev
#    (40) and DAggerFM's seed data data/expert_seed24 (the first 96 of IDS, the train environments 600-2999);
#    collection is deterministic, so these are the episodes this machine's runs trained on
# 2. both 16-epoch supervised runs, side by side on the GPU, resumed from the carried run folders where this
#    machine had got to (device, threads, prefetch and save interval may change when a run resumes; nothing else);
#    stopped after SUP_S seconds, keeping what was saved (state every 20 s)
# 3. if both finished their 16 epochs: DAggerFM for both (the plan's recipe: M 96, N_D 24, beta0 0.5, lr 3e-4,
#    mirror 0.5, in IDS), side by side, WORKERS/2 rollout processes each, a copy of every iteration kept; stopped
#    after DAGGER_S seconds; then each run's iterations 4..L averaged there (the plan's candidate)
# 4. $OUT/baselines.tgz.partNN (15 MB parts; rejoin with `cat baselines.tgz.part* | tar xz`): the supervised run
#    folders (state included: a later call or this machine resumes them), the DAggerFM logs, last checkpoints and
#    averages (not their datasets of rollouts, about 60 MB each: a DAggerFM run here is not resumed later);
#    and the runs' logs from $W; $OUT/call.log says what happened and when
# Speeds it plans on (docs/model.md; scripts/bench_reading.py): 17.8 expert episodes/s on 16 workers; GS-FPV and
# GS-FPV-MEM train at 4200-4600 frames/s each at batch 1 on an H200, two at once, once reading the episodes no
# longer holds them back (train.prefetch) -- 16 epochs of 49,686 frames in about 3-6 minutes.
# Here (DEVICE=cpu PY=.venv/bin/python WORKERS=2 RUNS=/tmp/x/runs DATA=/tmp/x/data, small TRAIN_EPISODES,
# DEV_EPISODES, SEED_EPISODES, EPOCHS and caps, and DAGGER_ARGS="--dagger.rollouts-per-iteration 2 ..." appended to
# the DAggerFM command, AVG_FROM=1) it runs the same steps, to try it.
set -u
OUT=${OUT:-/tmp/out}
DEVICE=${DEVICE:-cuda}
WORKERS=${WORKERS:-16}
PY=${PY:-python3}
RUNS=${RUNS:-runs}
DATA=${DATA:-data}
SUP_S=${SUP_S:-330}      # with the collection (about 45 s), set-up and packing, SUP_S + DAGGER_S <= 480 fits
DAGGER_S=${DAGGER_S:-150}  # one 10-minute call
EPOCHS=${EPOCHS:-16}
TRAIN_EPISODES=${TRAIN_EPISODES:-600}
SEED_EPISODES=${SEED_EPISODES:-96}
DEV_EPISODES=${DEV_EPISODES:-40}
DAGGER_ARGS=${DAGGER_ARGS:-}
AVG_FROM=${AVG_FROM:-4}
THREADS=${THREADS:-4}
PREFETCH=${PREFETCH:-4}
KINDS=${KINDS:-gs-fpv-mem gs-fpv}
W=${W:-/tmp/device_baselines}  # the runs' own logs (packed with them: the tool brings back at most 8 files)
mkdir -p "$OUT" "$RUNS" "$DATA" "$W"
L=$OUT/call.log
source scripts/device_log.sh || exit 1
ls -d "$RUNS"/*_sup16 2>/dev/null | tee -a "$L"
epochs_done() { [ -f "$RUNS/$1_sup16/log.jsonl" ] && wc -l < "$RUNS/$1_sup16/log.jsonl" || echo 0; }

stamp "1. expert data ($WORKERS workers)"
IDS=$($PY -c "from gsmn.world.spec import split_env_ids; print(','.join(map(str, split_env_ids('train', 3000)[600:])))")
$PY -m gsmn.cli collect --out "$DATA/expert_train" --split train --episodes "$TRAIN_EPISODES" --workers "$WORKERS" \
    2>&1 | tail -c 300 | tr '\r' '\n' | tail -1 | tee -a "$L"
$PY -m gsmn.cli collect --out "$DATA/expert_dev" --split dev --episodes "$DEV_EPISODES" --workers "$WORKERS" 2>&1 | tail -c 300 \
    | tr '\r' '\n' | tail -1 | tee -a "$L"
$PY -m gsmn.cli collect --out "$DATA/expert_seed24" --env-ids "$(echo "$IDS" | cut -d, -f1-"$SEED_EPISODES")" \
    --workers "$WORKERS" 2>&1 | tail -c 300 | tr '\r' '\n' | tail -1 | tee -a "$L"

stamp "2. supervised, $EPOCHS epochs each, for at most $SUP_S s (epochs done: $(for k in $KINDS; do echo -n "$k $(epochs_done $k) "; done))"
for k in $KINDS; do
    timeout -s TERM -k 30 "$SUP_S" $PY -m gsmn.cli train supervised --data "$DATA/expert_train" \
        --dev "$DATA/expert_dev" --run "$RUNS/${k}_sup16" --kind "$k" --train.epochs "$EPOCHS" --train.batch-size 1 \
        --train.threads "$THREADS" --train.device "$DEVICE" --train.prefetch "$PREFETCH" \
        --train.save-every-seconds 20 > "$W/${k}_sup16.log" 2>&1 &
done
wait
for k in $KINDS; do tr '\r' '\n' < "$W/${k}_sup16.log" | grep -v '%|' | tail -4 | tee -a "$L"; done
stamp "epochs done: $(for k in $KINDS; do echo -n "$k $(epochs_done $k) "; done)"

ready=1
for k in $KINDS; do [ "$(epochs_done "$k")" -ge "$EPOCHS" ] || ready=0; done
if [ "$ready" = 1 ] && [ "$DAGGER_S" -gt 0 ]; then
    stamp "3. DAggerFM for both for at most $DAGGER_S s"
    for k in $KINDS; do
        $PY scripts/keep_iterations.py "$RUNS/${k}_dagger_s28" > "$W/${k}_keep.log" 2>&1 &
        echo $! > "$W/${k}_keep.pid"
        timeout -s TERM -k 30 "$DAGGER_S" $PY -m gsmn.cli train dagger --init "$RUNS/${k}_sup16/checkpoint" \
            --data "$DATA/expert_seed24" --dev "$DATA/expert_dev" --run "$RUNS/${k}_dagger_s28" --env-ids "$IDS" \
            --train.batch-size 1 --train.threads "$THREADS" --train.device "$DEVICE" --train.prefetch "$PREFETCH" \
            --dagger.workers $((WORKERS / 2 > 0 ? WORKERS / 2 : 1)) --dagger.iterations 120 \
            --dagger.rollouts-per-iteration 24 --dagger.dataset-size 96 --dagger.beta0 0.5 \
            --train.learning-rate 0.0003 --train.mirror 0.5 $DAGGER_ARGS > "$W/${k}_dagger.log" 2>&1 &
    done
    wait $(jobs -p | grep -v -x -f <(cat "$W"/*_keep.pid))
    sleep 3
    for k in $KINDS; do
        kill "$(cat "$W/${k}_keep.pid")"
        tr '\r' '\n' < "$W/${k}_dagger.log" | grep -v '%|' | tail -3 | tee -a "$L"
        copies=$(ls -d "$RUNS/${k}_dagger_s28_it"* 2>/dev/null | sort -V | awk -F_it -v from="$AVG_FROM" '$NF >= from')
        if [ -n "$copies" ]; then
            $PY scripts/average_checkpoints.py $copies --out "$RUNS/${k}_dagger_s28_avg" 2>&1 | tee -a "$L"
        fi
    done
    stamp "DAggerFM copies: $(ls -d "$RUNS"/*_dagger_s28_it* 2>/dev/null | wc -l)"
fi

stamp "4. packing"
pack=()
for k in $KINDS; do
    pack+=("$RUNS/${k}_sup16")
    for p in log.jsonl config.json checkpoint; do [ -e "$RUNS/${k}_dagger_s28/$p" ] && pack+=("$RUNS/${k}_dagger_s28/$p"); done
    [ -d "$RUNS/${k}_dagger_s28_avg" ] && pack+=("$RUNS/${k}_dagger_s28_avg")
done
tar czf - "${pack[@]}" "$W" 2>/dev/null | split -b 15m -d - "$OUT/baselines.tgz.part"
ls -la "$OUT" | tee -a "$L"
stamp "done"
exit 0
