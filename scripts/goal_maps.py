"""Draw what checkpoints' grounding and goal heads make of dev episodes, side by side (docs/goal_maps.png).

    .venv/bin/pip install -e .[docs]       # matplotlib
    .venv/bin/python scripts/goal_maps.py --data data/expert_dev --episodes 6 \
        --checkpoint "sigmoid kernels=runs/a/checkpoint" --checkpoint "signed kernels=runs/b/checkpoint"

For each episode (a column) and checkpoint (two rows), the model runs over the expert's flight and, a third of the
way in, shows P(named) from the grounding head at every world-map cell and P(goal) from the goal head. White dots
are landmark centres, the red dot the named landmark, the magenta cross the goal. North is up.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from gsmn.model.batch import collate
from gsmn.model.checkpoint import load_checkpoint
from gsmn.model.labels import make_labels
from gsmn.training.store import EpisodeStore


def head_maps(model, vocabulary, sample) -> tuple[torch.Tensor, torch.Tensor, object]:
    """P(named) and P(goal) over the world map (n, n) a third of the way through `sample`, and its labels."""
    batch = collate([sample], vocabulary)
    with torch.inference_mode():
        out = model(batch.images, batch.T_world_camera, batch.K, batch.poses, batch.tokens, batch.lengths)
        t = sample.length // 3
        named = model.heads.grounding(out.relevance_map_w[0, t].permute(1, 2, 0)).softmax(-1)[..., 1]
        goal = model.heads.goal(out.goal_map_w[0, t].permute(1, 2, 0)).softmax(-1)[..., 1]
    return named, goal, make_labels(batch, model.geometry, model.image_size)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("data/expert_dev"))
    ap.add_argument("--episodes", type=int, default=6)
    ap.add_argument("--checkpoint", action="append", required=True, metavar="LABEL=FOLDER")
    ap.add_argument("--out", type=Path, default=Path("docs/goal_maps.png"))
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    checkpoints = []
    for item in args.checkpoint:
        label, folder = item.split("=", 1)
        model, _, vocabulary, _ = load_checkpoint(Path(folder))
        checkpoints.append((label, model, vocabulary))
    store = EpisodeStore(args.data)
    keys = store.keys()[: args.episodes]
    rows = 2 * len(checkpoints)
    fig, axes = plt.subplots(rows, len(keys), figsize=(2.4 * len(keys), 2.5 * rows), squeeze=False)
    for j, key in enumerate(keys):
        sample = store.read(key)
        for c, (label, model, vocabulary) in enumerate(checkpoints):
            named, goal, labels = head_maps(model, vocabulary, sample)
            cells = labels.landmark_cell_w[0]
            i = int(sample.instruction.landmark_index)
            for r, (image, what) in enumerate(((named, "P(named)"), (goal, "P(goal)"))):
                ax = axes[2 * c + r, j]
                ax.imshow(image.numpy(), vmin=0, vmax=1, cmap="viridis")
                ax.scatter(cells[:, 1], cells[:, 0], c="white", s=8)
                ax.scatter([cells[i, 1]], [cells[i, 0]], c="red", s=24)
                goal_cell = labels.goal_cell_w[0]
                ax.scatter([goal_cell[1]], [goal_cell[0]], c="magenta", marker="x", s=50)
                ax.set_xticks([])
                ax.set_yticks([])
                if j == 0:
                    ax.set_ylabel(f"{label}\n{what}", fontsize=8)
            if c == 0:
                axes[0, j].set_title(sample.instruction.text.removeprefix("go to the "), fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
