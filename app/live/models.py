"""The checkpoints the runner can fly (runner thread): which are offered, how a name becomes a folder, and the
models loaded from them, each with its auxiliary heads as numpy arrays for the page's layers and ground truth.

A bare name is a folder under `checkpoints/` (or a group's: `table2/no-ground`) or a finished fine-tuning run's
name (`run-3`); a path must lie under `checkpoints/` or be one the dashboard was started with or offers, so a
request cannot point the dashboard at any folder of the machine.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from app.live.commands import CheckpointInfo, RunnerError
from gsmn.config import RunConfig
from gsmn.experiments.recipe import describe_stage, read_stage
from gsmn.model.readout import Heads
from gsmn.world.landmarks import CATALOGUE

LIVE_KINDS = ("gsmn", "gsmn-no-plan")  # the models the runner flies: the page shows their maps
FIRST_PERSON_KINDS = ("gs-fpv", "gs-fpv-mem")  # evaluated and fine-tuned (app.jobs), not flown by the runner


@dataclass(frozen=True)
class MapHeads(Heads):
    """The auxiliary heads of a GSMN as numpy arrays (gsmn.attribution.Heads; `MapHeads.of(model)`), and the
    perception head's class names for the legend."""

    class_names: tuple[str, ...] = tuple(m.noun_phrase for m in CATALOGUE)


@dataclass
class LoadedModel:
    name: str
    path: Path
    policy: Any  # gsmn.model.policy.ModelPolicy
    heads: MapHeads
    meta: dict


def checkpoint_label(name: str, path: Path) -> str:
    """A readable name: a Table 2 system's label and where its programme stands (`gsmn experiment table2`), else
    the checkpoint's name."""
    stage = read_stage(path)
    return describe_stage(stage, path) if stage else name


class Checkpoints:
    """The checkpoints offered and the models loaded (by resolved path). `default_ref`: a folder, or a name under
    `root`; `require` makes a missing default an error instead of a message. Models load on the runner thread."""

    def __init__(self, config: RunConfig, root: str | Path = "checkpoints", default_ref: str | Path | None = "gsmn",
                 require: bool = False):
        self.config = config
        self.root = Path(root)
        self.default_ref = str(default_ref) if default_ref is not None else None
        self.require = require
        self.models: dict[str, LoadedModel] = {}
        self.extra: Callable[[], dict[str, Path]] | None = None  # e.g. fine-tuning runs', by name
        self.default: str | None = None  # key into self.models
        self.message = ""

    def _extra(self) -> dict[str, Path]:
        return self.extra() if self.extra else {}

    def listing(self) -> list[CheckpointInfo]:
        """Checkpoint folders under root, the default one, the extra ones, and any loaded."""
        found: dict[str, Path] = {}
        if self.root.is_dir():
            for meta in sorted(self.root.glob("*/meta.json")):
                found[meta.parent.name] = meta.parent
            for meta in sorted(self.root.glob("*/*/meta.json")):  # a group, e.g. table2/no-ground
                if not (meta.parent.parent / "meta.json").is_file():
                    found[f"{meta.parent.parent.name}/{meta.parent.name}"] = meta.parent
        if self.default_ref is not None and self.default_ref not in found:
            path = self.path_of(self.default_ref)  # e.g. a folder given by its path: listed once, by its name
            if path.is_dir() and path.resolve() not in {p.resolve() for p in found.values()}:
                found[self.default_ref] = path
        for name, path in self._extra().items():
            found.setdefault(name, path)
        known = {p.resolve() for p in found.values()}
        for m in self.models.values():
            if m.path.resolve() not in known:
                found.setdefault(m.name, m.path)
        return [self._info(name, path) for name, path in found.items()]

    def _info(self, name: str, path: Path) -> CheckpointInfo:
        key = str(path.resolve())
        try:
            meta = json.loads((path / "meta.json").read_text())
            error = None
        except (OSError, ValueError) as e:
            meta, error = {}, f"meta.json unreadable: {e}"
        return CheckpointInfo(name=name, path=str(path), kind=meta.get("kind"), created=meta.get("created"),
                              loaded=key in self.models, default=key == self.default, error=error,
                              metrics=meta.get("metrics") or {}, label=checkpoint_label(name, path))

    def path_of(self, ref: str) -> Path:
        """A bare name is a folder under root (unless only ./name is a checkpoint) or an extra checkpoint's name;
        else a path, which must be one this dashboard offers (`offered`); the refusal says the same whether the
        folder exists or not."""
        if not ref.strip():
            raise RunnerError("checkpoint is empty: name one (e.g. gsmn, table2/no-ground, run-3), or leave it out "
                              "for the default")
        extra = self._extra()
        try:
            if ref in extra and not (self.root / ref).is_dir():
                return extra[ref]
            candidate = self.root / ref
            if "/" not in ref and (candidate.is_dir() or not (Path(ref) / "meta.json").is_file()):
                return candidate
            if (candidate / "meta.json").is_file() and not (Path(ref) / "meta.json").is_file():  # table2/x
                return candidate
        except OSError as e:  # e.g. a name too long for the file system
            raise RunnerError(f"no checkpoint at {ref}: {e.strerror or e}") from e
        if not self.offered(Path(ref)):
            raise RunnerError(f"checkpoint {ref!r} is not one this dashboard offers: name a checkpoint under "
                              f"checkpoints/ (e.g. gsmn, table2/no-ground) or a finished fine-tuning run (run-N)")
        return Path(ref)

    def offered(self, path: Path) -> bool:
        """Under root, or the checkpoint the dashboard was started with, or one loaded or offered."""
        try:
            resolved = path.resolve()
            known = {Path(k) for k in self.models} | {p.resolve() for p in self._extra().values()}
            if self.default_ref is not None:
                known.add(Path(self.default_ref).resolve())
            return resolved.is_relative_to(self.root.resolve()) or resolved in known
        except (OSError, RuntimeError):
            return False

    def load_default(self) -> None:
        if self.default_ref is None:
            self.message = "No checkpoint: the expert flies, and there are no model maps."
            return
        try:
            self.default = self.model(self.default_ref).path.resolve().as_posix()
            m = self.models[self.default]
            self.message = f"Checkpoint {m.path} ({m.meta.get('kind')}, created {m.meta.get('created', '?')})."
        except RunnerError as e:
            if self.require:
                raise
            self.message = (f"No model loaded: {e}. The expert can still fly and every world can be explored; "
                            f"train one (docs/training.md) or pass --checkpoint.")

    def model(self, ref: str) -> LoadedModel:
        """The model of a checkpoint, loaded once (runner thread)."""
        path = self.path_of(ref)
        try:
            key = path.resolve().as_posix()
            found = path.is_dir()
        except OSError as e:
            raise RunnerError(f"no checkpoint at {path}: {e.strerror or e}") from e
        if key in self.models:
            return self.models[key]
        if not found:
            raise RunnerError(f"no checkpoint at {path}")
        self.models[key] = self._load(path)
        return self.models[key]

    def _load(self, path: Path) -> LoadedModel:
        from gsmn.model.checkpoint import CheckpointError, load_checkpoint
        from gsmn.model.gsmn import GSMN
        from gsmn.model.policy import ModelPolicy

        try:
            model, config, vocabulary, meta = load_checkpoint(path)
        except CheckpointError as e:
            raise RunnerError(str(e)) from e
        if not isinstance(model, GSMN):
            raise RunnerError(f"checkpoint {path} holds a {model.kind!r} model; the dashboard shows GSMN's maps and "
                              f"needs a 'gsmn' or 'gsmn-no-plan' checkpoint")
        cam = self.config.camera
        if model.image_size != (cam.width, cam.height):
            raise RunnerError(f"checkpoint {path} expects {model.image_size[0]}x{model.image_size[1]} images, the "
                              f"simulator renders {cam.width}x{cam.height}")
        name = path.name if path.parent.resolve() == self.root.resolve() else str(path)
        return LoadedModel(name, path, ModelPolicy(model, vocabulary, config), MapHeads.of(model), meta)
