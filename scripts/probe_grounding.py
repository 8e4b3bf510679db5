"""Does a model trained without J_ground still ground the instruction in its relevance map? A linear probe.

The grounding head (Linear(3 -> 2) on the relevance map at landmark cells, gsmn.model.heads) of a model trained
without J_ground is its initialisation, so failure attribution cannot read that model's relevance map. This script
fits the head afresh on the model's own recorded final relevance maps, with the model frozen: for every landmark
cell the camera covered, is it the landmark the instruction names? Two-fold cross-fitting (even and odd env ids),
so each episode is read by a probe fitted on the other half. It prints how often the named landmark scores above
every other landmark (the attribution's "grounded"), with the probe and with the untrained head, and the failures'
attributed stages with the probe standing in for the head. `--figure PATH` draws the first episodes' final
relevance maps, channel by channel, beside the probe's P(named), the landmarks marked (needs matplotlib).
`--verdicts PATH` writes each episode's verdicts as JSON; `--paired PATH` reads another model's and sets the two
probes' verdicts side by side over the episodes both saw (an exact sign test), the same method on both models:

    python scripts/probe_grounding.py --checkpoint checkpoints/table2/gsmn --record runs/table2/gsmn/record \
        --evaluation checkpoints/table2/gsmn/evaluation.json --verdicts runs/probe_gsmn.json
    python scripts/probe_grounding.py --checkpoint checkpoints/table2/no-ground ... --paired runs/probe_gsmn.json

    python scripts/probe_grounding.py --checkpoint checkpoints/table2/no-ground \
        --record runs/table2/no-ground/record --evaluation checkpoints/table2/no-ground/evaluation.json

`--record` is the folder of maps an evaluation with `--record` writes (`gsmn experiment table2` writes
runs/table2/<name>/record); `--evaluation` a `gsmn eval` JSON or a Table 2 `evaluation.json` of the same episodes.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np

from gsmn.attribution import (
    Heads,
    attribute_record,
    cell_of,
    load_trace,
    observed_cells,
    positive_probability,
    trace_path,
)
from gsmn.model.checkpoint import load_checkpoint
from gsmn.task.metrics import sign_test
from gsmn.world.spec import world_for_env


def cells(record: dict, maps, world) -> tuple[np.ndarray, np.ndarray]:
    """The relevance-map features (M, 3) of the landmark cells the camera covered, and whether each is named."""
    F, n = world.field_size, maps.relevance_map_w.shape[-1]
    seen = observed_cells(maps.semantic_map_w)
    xs, ys = [], []
    for lm in world.landmarks:
        r, c = cell_of(lm.x, lm.y, F, n)
        if seen[r, c]:
            xs.append(maps.relevance_map_w[:, r, c].astype(np.float64))
            ys.append(lm.noun_phrase == record["noun_phrase"])
    return np.array(xs).reshape(-1, 3), np.array(ys, bool)


def fit_logistic(x: np.ndarray, y: np.ndarray, l2: float = 1e-3, steps: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """Binary logistic regression by Newton's method, class-balanced; as Linear(C -> 2) weight (2, C), bias (2,)."""
    X = np.hstack([x, np.ones((len(x), 1))])
    w = np.zeros(X.shape[1])
    weight = np.where(y, 0.5 / max(y.sum(), 1), 0.5 / max((~y).sum(), 1))
    for _ in range(steps):
        p = 1 / (1 + np.exp(-X @ w))
        grad = X.T @ (weight * (p - y)) + l2 * w
        hess = (X * (weight * p * (1 - p))[:, None]).T @ X + l2 * np.eye(len(w))
        w -= np.linalg.solve(hess, grad)
    # Linear(C -> 2) whose class-1 minus class-0 logit is the regression's
    return np.stack([np.zeros(x.shape[1]), w[:-1]]).astype(np.float32), np.array([0.0, w[-1]], np.float32)


def figure(path: str, loaded: list, probes: list, rows: int = 4) -> None:
    """Each of the first `rows` episodes' final relevance map: its channels and the probe's P(named), with the
    named landmark (white star) and the others (red crosses); cells never covered are blank."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(rows, 4, figsize=(10, 2.6 * rows), squeeze=False)
    for (e, t, w), row in zip(loaded[:rows], axes, strict=False):
        R = t.maps.relevance_map_w.astype(np.float32)
        n, seen = R.shape[-1], observed_cells(t.maps.semantic_map_w)
        wt, b = probes[int(e["env_id"]) % 2]
        panels = [(R[i], f"channel {i}") for i in range(R.shape[0])]
        panels.append((positive_probability(R, wt, b), "probe: P(named)"))
        for ax, (values, title) in zip(row, panels, strict=False):
            ax.imshow(np.where(seen, values, np.nan), cmap="viridis")
            for lm in w.landmarks:
                r, c = cell_of(lm.x, lm.y, w.field_size, n)
                named = lm.noun_phrase == e["noun_phrase"]
                ax.plot(c, r, "w*" if named else "r+", ms=10 if named else 7, mec="k" if named else None)
            ax.set_title(f"env {e['env_id']}, {title}", fontsize=9)
            ax.set_xticks([])
            ax.set_yticks([])
        row[0].set_ylabel(e["noun_phrase"], fontsize=9)
    fig.suptitle("Final relevance maps of a model trained without J_ground (north up; star: the named landmark)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    print(f"wrote {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--record", required=True, help="the maps recorded by the evaluation (--record)")
    ap.add_argument("--evaluation", required=True, help="the evaluation's JSON (its episodes)")
    ap.add_argument("--figure", default=None, help="draw the first episodes' relevance maps to this PNG")
    ap.add_argument("--verdicts", default=None, help="write each episode's verdicts to this JSON")
    ap.add_argument("--paired", default=None, help="another model's --verdicts JSON: compare the probes' verdicts")
    args = ap.parse_args()

    model, config, *_ = load_checkpoint(args.checkpoint)
    heads = Heads.of(model)
    episodes = [e for e in json.loads(open(args.evaluation).read())["episodes"]
                if trace_path(args.record, int(e["env_id"])).is_file()]
    if not episodes:
        raise SystemExit(f"no recorded maps in {args.record} for the episodes of {args.evaluation}")
    loaded = [(e, load_trace(trace_path(args.record, int(e["env_id"]))), world_for_env(int(e["env_id"]), config.world))
              for e in episodes]

    folds = [[item for item in loaded if int(item[0]["env_id"]) % 2 == k] for k in (0, 1)]
    probes = []
    for k in (0, 1):  # fitted on the other fold
        xy = [cells(e, t.maps, w) for e, t, w in folds[1 - k]]
        probes.append(fit_logistic(np.concatenate([x for x, _ in xy]), np.concatenate([y for _, y in xy])))

    # the attribution's own verdicts (`Attribution.grounded`: P(named) at the named landmark above every other
    # landmark's), read with the model's head as if trained and with the probe fitted on the other fold
    own = "trained head" if heads.grounding_trained else "untrained head"
    rows = {own: {}, "probe": {}}  # env id -> grounded (None: the named landmark never seen)
    stages = Counter()
    for k in (0, 1):
        readers = {own: replace(heads, grounding_trained=True),
                   "probe": replace(heads, grounding_w=probes[k][0], grounding_b=probes[k][1], grounding_trained=True)}
        for e, t, _ in folds[k]:
            for name, reader in readers.items():
                a = attribute_record(e, t, reader, config)
                rows[name][int(e["env_id"])] = a.grounded if a.observed else None
                if name == "probe" and not e["success"]:
                    stages[a.stage] += 1
    n_landmarks = np.mean([len(w.landmarks) for _, _, w in loaded])
    print(f"{args.checkpoint}: {len(loaded)} episodes, {n_landmarks:.1f} landmarks per world")
    for name, verdicts in rows.items():
        seen = [v for v in verdicts.values() if v is not None]
        print(f"  named landmark above every other landmark ({name}): {sum(seen)} of {len(seen)} episodes where "
              f"it was seen ({100 * sum(seen) / max(len(seen), 1):.1f} %)")
    print("  failures by stage with the probe as grounding head: "
          + ", ".join(f"{s} {c}" for s, c in sorted(stages.items(), key=lambda kv: -kv[1])))
    for k, (wt, b) in enumerate(probes):
        print(f"  probe for fold {k}: logit(named) = {' + '.join(f'{v:.2f} r{i}' for i, v in enumerate(wt[1]))} "
              f"+ {b[1]:.2f}")
    if args.verdicts:
        with open(args.verdicts, "w") as f:
            json.dump({"checkpoint": args.checkpoint, "verdicts": rows}, f)
        print(f"wrote {args.verdicts}")
    if args.paired:
        print(paired(rows["probe"], args.paired, args.checkpoint))
    if args.figure:
        figure(args.figure, loaded, probes)


def paired(mine: dict[int, bool | None], path: str, name: str) -> str:
    """This model's probe verdicts beside another's (a --verdicts file) over the episodes both saw the named
    landmark in: how many only one of them grounds, and the exact sign test of those."""
    other = json.loads(Path(path).read_text())
    theirs = {int(k): v for k, v in other["verdicts"]["probe"].items()}
    both = [k for k in mine if mine[k] is not None and theirs.get(k) is not None]
    if not both:
        raise SystemExit(f"{path} shares no episode with {name} where both saw the named landmark")
    only_mine, only_theirs = sum(mine[k] and not theirs[k] for k in both), sum(theirs[k] and not mine[k] for k in both)
    p = sign_test(only_mine, only_theirs)
    return (f"  probe, paired with {other['checkpoint']} over {len(both)} episodes: grounded by {name} only "
            f"{only_mine}, by {other['checkpoint']} only {only_theirs}, sign test p {p:.2g}")


if __name__ == "__main__":
    main()
