"""Average the weights of checkpoints of one model (e.g. several DAggerFM iterations of one run) into a new one
(`gsmn.model.checkpoint.average_checkpoints`; docs/training.md, "Averaging iterations").

    python scripts/average_checkpoints.py runs/gsmn_dagger_stop_it6 runs/gsmn_dagger_stop_it9 \
        runs/gsmn_dagger_stop_it12 --out runs/gsmn_avg_6_9_12
"""

from __future__ import annotations

import argparse

from gsmn.model.checkpoint import average_checkpoints


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoints", nargs="+", help="checkpoint folders of one model")
    parser.add_argument("--out", required=True, help="the averaged checkpoint's folder")
    args = parser.parse_args()
    out = average_checkpoints(args.checkpoints, args.out)
    print(f"{out}: the mean of {len(args.checkpoints)} checkpoints' weights")


if __name__ == "__main__":
    main()
