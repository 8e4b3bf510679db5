#!/usr/bin/env bash
# The GSMN training pipeline on this machine's CPU, resumable at every step: run it again after a kill
# or in a new session and it continues where it stopped. Sizes are chosen from measured throughput
# (docs/training.md): 700 train environments, 10 epochs.
set -euo pipefail
cd "$(dirname "$0")/.."
KIND=${KIND:-gsmn}
EPOCHS=${EPOCHS:-10}
TRAIN_EPISODES=${TRAIN_EPISODES:-700}
.venv/bin/gsmn collect --out data/expert_train --split train --episodes "$TRAIN_EPISODES" --workers 2
.venv/bin/gsmn collect --out data/expert_dev --split dev --episodes 60 --workers 2
.venv/bin/gsmn train supervised --data data/expert_train --dev data/expert_dev --run "runs/${KIND}_sup" \
    --kind "$KIND" --train.epochs "$EPOCHS"
