#!/usr/bin/env bash
# The GSMN training pipeline on this machine's CPU, resumable at every step: run it again after a kill
# or in a new session and it continues where it stopped. Sizes are chosen from measured throughput
# (docs/training.md): 600 train and 40 dev environments, 8 epochs, one episode per batch, then DAggerFM
# from the supervised checkpoint (10 iterations, M 192, N_D 24, beta0 0.75).
#
#   KIND=gs-fpv-mem bash scripts/train_gsmn.sh        # the baselines the same way
#   EPOCHS=16 bash scripts/train_gsmn.sh              # extend a finished supervised run (DAgger then starts
#                                                     # a new run folder: remove the old runs/KIND_dagger)
#   DAGGER_ITERATIONS=0 bash scripts/train_gsmn.sh    # supervised only
#   INIT=runs/other/checkpoint bash scripts/train_gsmn.sh      # start from another run's weights
#   THREADS=1 WORKERS=1 KIND=gs-fpv bash scripts/train_gsmn.sh # one core: two runs side by side on two cores
set -euo pipefail
cd "$(dirname "$0")/.."
KIND=${KIND:-gsmn}
EPOCHS=${EPOCHS:-8}
BATCH=${BATCH:-1}
TRAIN_EPISODES=${TRAIN_EPISODES:-600}
DEV_EPISODES=${DEV_EPISODES:-40}
RUN=${RUN:-runs/${KIND}_sup_b${BATCH}}
INIT=${INIT:-}
DAGGER_ITERATIONS=${DAGGER_ITERATIONS:-10}
THREADS=${THREADS:-2}
WORKERS=${WORKERS:-2}
.venv/bin/gsmn collect --out data/expert_train --split train --episodes "$TRAIN_EPISODES" --workers "$WORKERS"
.venv/bin/gsmn collect --out data/expert_dev --split dev --episodes "$DEV_EPISODES" --workers "$WORKERS"
.venv/bin/gsmn train supervised --data data/expert_train --dev data/expert_dev --run "$RUN" \
    --kind "$KIND" --train.epochs "$EPOCHS" --train.batch-size "$BATCH" --train.threads "$THREADS" ${INIT:+--init "$INIT"}
if [ "$DAGGER_ITERATIONS" -gt 0 ]; then
    .venv/bin/gsmn train dagger --init "$RUN/checkpoint" --data data/expert_train --dev data/expert_dev \
        --run "runs/${KIND}_dagger" --train.batch-size "$BATCH" --train.threads "$THREADS" --dagger.workers "$WORKERS" \
        --dagger.iterations "$DAGGER_ITERATIONS" \
        --dagger.rollouts-per-iteration 24 --dagger.dataset-size 192 --dagger.beta0 0.75
fi
