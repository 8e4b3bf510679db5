"""Build a GS-FPV-MEM checkpoint from a trained GS-FPV checkpoint (a warm start; not in the paper).

GS-FPV-MEM is GS-FPV with an LSTM over the flattened relevance and goal maps whose 32 outputs join the
perceptron's extra input (`gsmn/model/fpv.py`). This copies every weight the two share, leaves the LSTM at its
default initialisation and sets the perceptron's weights on the LSTM outputs to zero, so the new network flies
exactly as the GS-FPV it came from until training gives the memory a say (docs/training.md, "GS-FPV-MEM
warm-started from GS-FPV"):

    perceptron.hidden: [maps 2880; sentence 30]            -> [maps; sentence; memory 32 (zero)]
    perceptron.out:    [maps; sentence; hidden 32]          -> [maps; sentence; memory 32 (zero); hidden]

    python scripts/warm_start_memory.py checkpoints/gs-fpv --out runs/w22/gs-fpv-mem --seed 0
"""

from __future__ import annotations

import argparse
from pathlib import Path

from gsmn.model.checkpoint import load_checkpoint, save_checkpoint
from gsmn.model.fpv import memory_from_fpv


def warm_start_memory(fpv_folder: str | Path, out: str | Path, seed: int = 0) -> Path:
    """Write a GS-FPV-MEM checkpoint at `out` that computes the same actions as the GS-FPV at `fpv_folder`."""
    fpv, config, vocabulary, _ = load_checkpoint(fpv_folder)
    try:
        mem = memory_from_fpv(fpv, seed)
    except ValueError as e:
        raise SystemExit(f"{fpv_folder}: {e}") from e
    return save_checkpoint(out, mem, config, vocabulary,
                           meta={"warm_started_from": str(fpv_folder), "lstm_seed": seed})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("gs_fpv", help="a GS-FPV checkpoint folder")
    parser.add_argument("--out", required=True, help="the GS-FPV-MEM checkpoint folder to write")
    parser.add_argument("--seed", type=int, default=0, help="seed of the LSTM's initialisation")
    args = parser.parse_args()
    print(f"{warm_start_memory(args.gs_fpv, args.out, args.seed)}: GS-FPV-MEM warm-started from {args.gs_fpv}")


if __name__ == "__main__":
    main()
