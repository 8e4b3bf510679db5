"""Checkpoints: a folder that loads from its path alone (house style; LeRobot-like).

    weights.safetensors   the model's tensors (safetensors: never unpickled)
    config.json           the resolved RunConfig (RunConfig.to_dict)
    vocabulary.json       the word list the token ids refer to
    meta.json             {"format", "kind", "created", "code_version", "metrics", ...free-form}
    optimizer.safetensors optional: the training run's optimizer state (its tensors as safetensors, its
                          hyper-parameters as JSON in the file's metadata: never unpickled), so that training can
                          go on from the checkpoint as if it had not stopped (`gsmn train ... --init C
                          --init-optimizer`); a legacy optimizer.pt is still read, with weights_only=True

`save_checkpoint` writes into a temporary sibling folder and renames it into place, so a reader never sees a
half-written checkpoint. `load_checkpoint` raises `CheckpointError` naming the folder and what is wrong for a
missing or malformed file, an unknown kind, or weights that do not fit the model the config and kind describe.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import uuid
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from gsmn.config import ConfigError, RunConfig
from gsmn.model.models import KINDS, Model, build_model
from gsmn.model.policy import ModelPolicy
from gsmn.model.vocabulary import Vocabulary

FORMAT = 1
FILES = ("weights.safetensors", "config.json", "vocabulary.json", "meta.json")
OPTIMIZER_FILE = "optimizer.safetensors"
LEGACY_OPTIMIZER_FILE = "optimizer.pt"  # written by older code: torch.save, read with weights_only=True


class CheckpointError(ValueError):
    """A checkpoint folder is missing, malformed, or does not fit its model."""


def code_version() -> str:
    """`git describe --always --dirty` of this source tree, or "unknown"."""
    try:
        out = subprocess.run(["git", "describe", "--always", "--dirty", "--tags"], cwd=Path(__file__).parent,
                             capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() else "unknown"


def on_cpu(value: Any) -> Any:
    """A state_dict (nested dicts, lists and tensors) with its tensors on the CPU: what a run trained on a GPU saves,
    so that a machine without one reads it."""
    if isinstance(value, torch.Tensor):
        return value.detach().cpu()
    if isinstance(value, dict):
        return {k: on_cpu(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(on_cpu(v) for v in value)
    return value


def save_optimizer_state(path: str | Path, state_dict: dict[str, Any]) -> None:
    """An optimizer's state_dict as a safetensors file: every tensor of `state` under "state/<param>/<name>", the
    non-tensor entries and `param_groups` as JSON in the metadata. Nothing in it is ever unpickled."""
    tensors, scalars = {}, {}
    for param, entries in state_dict["state"].items():
        for name, value in entries.items():
            if isinstance(value, torch.Tensor):
                tensors[f"state/{param}/{name}"] = value.detach().cpu().contiguous()
            else:
                scalars[f"{param}/{name}"] = value
    save_file(tensors, str(path), metadata={"param_groups": json.dumps(state_dict["param_groups"]),
                                            "scalars": json.dumps(scalars), "format": "optimizer-1"})


def read_optimizer_state(path: str | Path) -> dict[str, Any]:
    """The state_dict `save_optimizer_state` wrote (a legacy .pt file: torch.load with weights_only=True)."""
    path = Path(path)
    if path.suffix == ".pt":
        return torch.load(path, weights_only=True, map_location="cpu")
    from safetensors import safe_open

    state: dict[int, dict[str, Any]] = {}
    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata() or {}
        if meta.get("format") != "optimizer-1":
            raise ValueError(f"{path.name} is not an optimizer state file (format {meta.get('format')!r})")
        for key in f.keys():
            _, param, name = key.split("/", 2)
            state.setdefault(int(param), {})[name] = f.get_tensor(key)
    for key, value in json.loads(meta["scalars"]).items():
        param, name = key.split("/", 1)
        state.setdefault(int(param), {})[name] = value
    return {"state": state, "param_groups": json.loads(meta["param_groups"])}


def optimizer_file(folder: str | Path) -> Path | None:
    """The optimizer state file in a checkpoint or run-state folder (safetensors, else a legacy .pt), or None."""
    for name in (OPTIMIZER_FILE, LEGACY_OPTIMIZER_FILE):
        if (Path(folder) / name).is_file():
            return Path(folder) / name
    return None


def cpu_weights(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The model's state_dict as contiguous CPU tensors, as safetensors files hold them."""
    return {k: v.contiguous() for k, v in on_cpu(model.state_dict()).items()}


def save_checkpoint(folder: str | Path, model: Model, config: RunConfig, vocabulary: Vocabulary,
                    meta: dict[str, Any] | None = None, optimizer_state: dict[str, Any] | None = None) -> Path:
    """Write a checkpoint folder atomically (replacing an existing checkpoint there). `meta` is free-form JSON
    (e.g. {"metrics": {...}, "epoch": 3}); kind, created, code_version and format are filled in.
    `optimizer_state` (an optimizer's state_dict) is written beside the weights when given."""
    folder = Path(folder)
    if config.model != model.config.model or config.world.field_size != model.config.world.field_size \
            or (config.camera.width, config.camera.height) != model.image_size:
        raise ValueError("save_checkpoint: `config` does not describe this model (model, field or camera sizes "
                         "differ from the config the model was built with)")
    if folder.exists() and any(folder.iterdir()) and not (folder / "meta.json").is_file():
        raise CheckpointError(f"{folder} exists and is not a checkpoint; refusing to replace it")
    full_meta = {"metrics": {}, **(meta or {}), "format": FORMAT, "kind": model.kind,
                 "created": datetime.now(UTC).isoformat(timespec="seconds"), "code_version": code_version()}
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = folder.parent / f".{folder.name}.tmp-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        save_file(cpu_weights(model), str(tmp / "weights.safetensors"),
                  metadata={"kind": model.kind, "format": str(FORMAT)})
        (tmp / "config.json").write_text(config.to_json() + "\n")
        (tmp / "vocabulary.json").write_text(vocabulary.to_json() + "\n")
        (tmp / "meta.json").write_text(json.dumps(full_meta, indent=1, sort_keys=True) + "\n")
        if optimizer_state is not None:
            save_optimizer_state(tmp / OPTIMIZER_FILE, optimizer_state)
        if folder.exists():
            old = folder.parent / f".{folder.name}.old-{uuid.uuid4().hex[:8]}"
            os.rename(folder, old)
            os.rename(tmp, folder)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(tmp, folder)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return folder


def average_checkpoints(folders: list[str | Path], out: str | Path) -> Path:
    """Write the mean of several checkpoints' weights (of one kind, vocabulary and model config, e.g. several
    DAggerFM iterations of one run) as a new checkpoint `out`: checkpoint averaging (Polyak; Izmailov et al. 2018,
    "Averaging weights leads to wider optima"). Floating-point tensors are averaged, others taken from the last
    (GSMN has none: GroupNorm keeps no running statistics). The config and vocabulary are the last checkpoint's;
    there is no optimizer state (a mean of Adam moments means nothing); meta.json names the sources and has no
    metrics (the sources' dev metrics are not the mean's)."""
    if not folders:
        raise ValueError("average_checkpoints: no checkpoints given")
    loaded = [load_checkpoint(f) for f in folders]
    model, config, vocabulary, _ = loaded[-1]
    _, first_config, first_vocabulary, first_meta = loaded[0]
    for folder, (_, c, v, m) in zip(folders, loaded, strict=True):
        if (m["kind"], v, c.model) != (first_meta["kind"], first_vocabulary, first_config.model):
            raise CheckpointError(f"checkpoint {folder}: its kind, vocabulary or model config differs from "
                                  f"{folders[0]}'s; only checkpoints of one model can be averaged")
    states = [m.state_dict() for m, *_ in loaded]
    model.load_state_dict({name: torch.stack([s[name].float() for s in states]).mean(0).to(t.dtype)
                           if t.is_floating_point() else t for name, t in states[-1].items()})
    return save_checkpoint(out, model, config, vocabulary,
                           meta={"averaged_from": [str(f) for f in folders]})  # no metrics: nobody measured it yet


def checkpoint_iteration(meta_text: str) -> int | None:
    """The DAggerFM iteration (or supervised epoch) a checkpoint's meta.json says it was written after, or None."""
    metrics = json.loads(meta_text).get("metrics", {})
    n = metrics.get("iteration", metrics.get("epoch"))
    return None if n is None else int(n)


def keep_iteration(run: str | Path) -> Path | None:
    """Copy a training run's checkpoint (weights, config, vocabulary, meta; not the Adam state) to RUN_itN when its
    iteration (or epoch) N has no copy yet, for averaging (`gsmn keep-iterations` polls this beside a training run).
    Returns the copy, or None. The run replaces its checkpoint by a rename, so a copy is kept only if the run's
    meta.json was the same before and after it (and the same as the copy's); one taken while the checkpoint was
    being replaced is dropped, to be taken again on the next call."""
    run = Path(run)
    meta = run / "checkpoint" / "meta.json"
    try:
        before = meta.read_text()
        n = checkpoint_iteration(before)
    except (OSError, json.JSONDecodeError):  # not written yet, or being replaced
        return None
    dst = run.parent / f"{run.name}_it{n}"
    if n is None or dst.exists():
        return None
    tmp = run.parent / f".{dst.name}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        shutil.copytree(run / "checkpoint", tmp, ignore=shutil.ignore_patterns(OPTIMIZER_FILE, LEGACY_OPTIMIZER_FILE))
        unchanged = meta.read_text() == before == (tmp / "meta.json").read_text()
    except OSError:
        unchanged = False
    if not unchanged:  # replaced while copying: try again next time
        shutil.rmtree(tmp, ignore_errors=True)
        return None
    tmp.rename(dst)
    return dst


def _read_json(folder: Path, name: str) -> Any:
    path = folder / name
    if not path.is_file():
        raise CheckpointError(f"checkpoint {folder}: {name} is missing")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"checkpoint {folder}: {name} is not valid JSON ({e})") from e


def read_checkpoint_kind(folder: str | Path) -> str:
    """The model kind a checkpoint folder's meta.json names, without loading the weights (CheckpointError if the
    folder is no checkpoint or names no known kind)."""
    return _read_meta(Path(folder))[1]


def _read_meta(folder: Path) -> tuple[dict[str, Any], str]:
    """(meta.json, its kind) of a checkpoint folder, checked: the folder exists and the kind is known."""
    if not folder.is_dir():
        raise CheckpointError(f"checkpoint {folder}: no such folder")
    meta = _read_json(folder, "meta.json")
    if not isinstance(meta, dict):
        raise CheckpointError(f"checkpoint {folder}: meta.json must hold an object")
    kind = meta.get("kind")
    if kind not in KINDS:
        raise CheckpointError(f"checkpoint {folder}: meta.json names kind {kind!r}; known kinds: {', '.join(KINDS)}")
    return meta, kind


def read_checkpoint_config(folder: str | Path) -> RunConfig:
    """The RunConfig a checkpoint was made with (its config.json), without loading the weights."""
    folder = Path(folder)
    raw_config = _read_json(folder, "config.json")
    if isinstance(raw_config, dict) and isinstance(raw_config.get("model"), dict):
        # Written before model.filter_activation existed, when the kernels always went through a sigmoid.
        raw_config["model"].setdefault("filter_activation", "sigmoid")
    try:
        return RunConfig.from_dict(raw_config)
    except (ConfigError, TypeError, AttributeError) as e:
        raise CheckpointError(f"checkpoint {folder}: config.json is not a valid RunConfig ({e})") from e


def with_model_of(config: RunConfig, init: str | Path) -> RunConfig:
    """`config` with the model section of the checkpoint `init`: a run that starts from a checkpoint keeps the
    architecture its weights were trained with (the kernels' activation, say, which no weight shape reveals), and
    its own checkpoints record it."""
    return dataclasses.replace(config, model=read_checkpoint_config(init).model)


def load_optimizer_state(folder: str | Path) -> dict[str, Any]:
    """The optimizer state saved in a checkpoint folder (tensors and plain containers only: never code)."""
    path = optimizer_file(folder)
    if path is None:
        raise CheckpointError(f"checkpoint {folder}: holds no optimizer state ({OPTIMIZER_FILE}); it was saved "
                              "without one, so training from it must start a fresh optimizer (leave out "
                              "--init-optimizer)")
    try:
        return read_optimizer_state(path)  # on the CPU: Adam moves it onto its parameters' device
    except Exception as e:  # damaged files fail in many types
        raise CheckpointError(f"checkpoint {folder}: {path.name} is unreadable ({e})") from e


def load_checkpoint(folder: str | Path, device: str | torch.device = "cpu"
                    ) -> tuple[Model, RunConfig, Vocabulary, dict[str, Any]]:
    """(model in eval mode, config, vocabulary, meta) from a checkpoint folder."""
    folder = Path(folder)
    meta, kind = _read_meta(folder)
    if meta.get("format") != FORMAT:
        raise CheckpointError(f"checkpoint {folder}: format {meta.get('format')!r}, this code reads format {FORMAT}")
    config = read_checkpoint_config(folder)
    try:
        vocabulary = Vocabulary.from_json((folder / "vocabulary.json").read_text())
    except FileNotFoundError as e:
        raise CheckpointError(f"checkpoint {folder}: vocabulary.json is missing") from e
    except (ValueError, TypeError) as e:
        raise CheckpointError(f"checkpoint {folder}: vocabulary.json is malformed ({e})") from e
    weights = folder / "weights.safetensors"
    if not weights.is_file():
        raise CheckpointError(f"checkpoint {folder}: weights.safetensors is missing")
    try:
        tensors = load_file(str(weights), device=str(device))
    except (SafetensorError, OSError, ValueError) as e:
        raise CheckpointError(f"checkpoint {folder}: weights.safetensors cannot be read ({e})") from e
    model = build_model(kind, config, vocabulary).to(device)
    _check_weights(folder, kind, model, tensors)
    model.load_state_dict(tensors, strict=True)
    model.eval()
    return model, config, vocabulary, meta


def _check_weights(folder: Path, kind: str, model: Model, tensors: dict[str, torch.Tensor]) -> None:
    expected = model.state_dict()
    missing = sorted(set(expected) - set(tensors))
    unexpected = sorted(set(tensors) - set(expected))
    wrong = [f"{k} (saved {tuple(tensors[k].shape)}, model {tuple(expected[k].shape)})"
             for k in sorted(set(expected) & set(tensors)) if tensors[k].shape != expected[k].shape]
    if not (missing or unexpected or wrong):
        # a diverged training run saves NaN or infinite weights: such a model loads, but "flies" by sitting still
        broken = [k for k in sorted(tensors) if tensors[k].is_floating_point() and not torch.isfinite(tensors[k]).all()]
        if broken:
            raise CheckpointError(f"checkpoint {folder}: weights.safetensors holds NaN or infinite values in "
                                  f"{', '.join(broken[:5])}" + (f", ... ({len(broken)} tensors)" if len(broken) > 5
                                                                else ""))
        return

    def listing(names: list[str]) -> str:
        return ", ".join(names[:5]) + (f", ... ({len(names)} in all)" if len(names) > 5 else "")

    problems = [f"missing {listing(missing)}" if missing else "", f"unexpected {listing(unexpected)}" if unexpected
                else "", f"wrong shape {listing(wrong)}" if wrong else ""]
    raise CheckpointError(f"checkpoint {folder}: weights.safetensors does not fit a {kind!r} model built from its "
                          f"config.json and vocabulary.json: " + "; ".join(p for p in problems if p))


def load_policy(folder: str | Path) -> ModelPolicy:
    """The policy of a checkpoint folder (named after its kind)."""
    model, config, vocabulary, _ = load_checkpoint(folder)
    return ModelPolicy(model, vocabulary, config)
