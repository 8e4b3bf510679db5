"""Typed configuration for every component, with named presets.

One frozen dataclass per component (world, drone, camera, ...), nested into `RunConfig`. Each field
carries its help text in `metadata["help"]`; `gsmn.cli` turns the fields into command-line flags
(`--camera.pitch-deg 27`), so nothing here is a global parameter dict. Every config validates itself in
`__post_init__` and fails with a clear message before any simulation starts.

Presets: `paper` (the paper's and the original code's numbers, see docs/design.md for departures) and
`tiny` (the same world, cheaper rendering, for tests and CI). Fine-tuning presets (`FINE_TUNE_PRESETS`: tiny, small,
paper): the sizes of a DAggerFM run the dashboard launches, as DaggerConfig and TrainConfig values.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import types
import typing
from dataclasses import dataclass, field
from typing import Any

_UNSET = object()


def _f(default: Any, help: str, saved_without: Any = _UNSET) -> Any:  # noqa: A002 - "help" mirrors argparse
    """A config field. `saved_without`: the value a saved config that lacks the field meant (a field added later
    whose new default differs from what older files ran with); `from_dict` reads such a file so."""
    metadata = {"help": help} if saved_without is _UNSET else {"help": help, "saved_without": saved_without}
    return field(default=default, metadata=metadata)


class ConfigError(ValueError):
    """A configuration value is out of range or inconsistent."""


def _check(cond: bool, msg: str) -> None:
    if not cond:
        raise ConfigError(msg)


@dataclass(frozen=True)
class WorldConfig:
    """Procedural landmark fields (paper: Experimental Setup / Environment)."""

    field_size: float = _f(30.0, "edge length of the square field in metres")
    min_landmarks: int = _f(6, "fewest landmarks drawn per environment")
    max_landmarks: int = _f(13, "most landmarks drawn per environment (fewer may fit; see docs/design.md)")
    edge_margin: float = _f(2.7, "landmark centres keep this far from the field edges (m)")
    landmark_gap: float = _f(1.8, "centres are at least r_i + r_j + this apart (m)")
    start_clearance: float = _f(4.5, "centres are at least r + this from the start position (m)")
    radius_scale_min: float = _f(1.0, "landmarks are scaled by U(min, max)")
    radius_scale_max: float = _f(1.3, "landmarks are scaled by U(min, max)")
    placement_candidates: int = _f(1000, "random candidate positions tried per landmark before it is dropped")
    min_lakes: int = _f(1, "fewest decorative lakes")
    max_lakes: int = _f(4, "most decorative lakes")
    lake_radius_min: float = _f(1.5, "smallest lake semi-axis (m)")
    lake_radius_max: float = _f(4.0, "largest lake semi-axis (m)")
    seed: int = _f(0, "base seed; the world of environment id N is drawn from SeedSequence([seed, N])")

    def __post_init__(self) -> None:
        _check(self.field_size > 0, f"world.field_size must be positive, got {self.field_size}")
        _check(1 <= self.min_landmarks <= self.max_landmarks,
               f"need 1 <= world.min_landmarks <= world.max_landmarks, got {self.min_landmarks}, "
               f"{self.max_landmarks}")
        _check(0 <= self.edge_margin < self.field_size / 2, "world.edge_margin must be in [0, field_size/2)")
        _check(0 < self.radius_scale_min <= self.radius_scale_max,
               "need 0 < world.radius_scale_min <= world.radius_scale_max")
        _check(0 <= self.min_lakes <= self.max_lakes, "need 0 <= world.min_lakes <= world.max_lakes")
        _check(0 < self.lake_radius_min <= self.lake_radius_max,
               "need 0 < world.lake_radius_min <= world.lake_radius_max")
        _check(self.placement_candidates >= 1, "world.placement_candidates must be >= 1")


@dataclass(frozen=True)
class DroneConfig:
    """Quadcopter dynamics and its cascaded velocity controller (paper: Hyper-parameters)."""

    altitude: float = _f(5.0, "altitude the controller holds (m)")
    max_forward_velocity: float = _f(1.6, "forward velocity limit (m/s); no reversing")
    max_yaw_rate: float = _f(2.44, "yaw rate limit (rad/s)")
    control_hz: float = _f(5.0, "action rate (Hz); physics is sub-stepped between actions")
    physics_dt: float = _f(0.005, "MuJoCo time step (s)")
    mass: float = _f(1.0, "total mass (kg)")
    arm_length: float = _f(0.18, "centre to rotor distance (m), for inertia and looks")
    max_tilt_deg: float = _f(25.0, "largest roll/pitch the velocity loop may ask for (deg)")
    velocity_gain: float = _f(3.0, "horizontal velocity loop gain (1/s)")
    altitude_kp: float = _f(8.0, "altitude loop proportional gain (1/s^2)")
    altitude_kd: float = _f(5.0, "altitude loop derivative gain (1/s)")
    attitude_kp: float = _f(150.0, "roll/pitch loop proportional gain (1/s^2)")
    attitude_kd: float = _f(22.0, "roll/pitch loop derivative gain (1/s)")
    yaw_rate_gain: float = _f(30.0, "yaw-rate loop gain (1/s)")

    def __post_init__(self) -> None:
        _check(self.altitude > 0, "drone.altitude must be positive")
        _check(self.max_forward_velocity > 0 and self.max_yaw_rate > 0, "drone velocity limits must be positive")
        _check(self.control_hz > 0 and self.physics_dt > 0, "drone.control_hz and drone.physics_dt must be > 0")
        substeps = 1.0 / (self.control_hz * self.physics_dt)
        _check(abs(substeps - round(substeps)) < 1e-6,
               f"1 / (control_hz * physics_dt) must be an integer number of substeps, got {substeps}")
        _check(0 < self.max_tilt_deg < 60, "drone.max_tilt_deg must be in (0, 60)")

    @property
    def substeps(self) -> int:
        """Physics steps per action."""
        return round(1.0 / (self.control_hz * self.physics_dt))


SHADOW_METHODS = ("mujoco", "baked")


@dataclass(frozen=True)
class CameraConfig:
    """The forward camera (paper: 256x144 RGB first-person images)."""

    width: int = _f(256, "image width (px)")
    height: int = _f(144, "image height (px)")
    hfov_deg: float = _f(90.0, "horizontal field of view (deg)")
    pitch_deg: float = _f(27.0, "downward pitch of the camera relative to the body (deg)")
    forward_offset: float = _f(0.1, "camera position ahead of the body centre (m)")
    shadows: bool = _f(True, "render shadows")
    shadow_size: int = _f(1024, "shadow map size (MuJoCo's default 4096 costs ~70 ms a frame on CPU)")
    shadow_method: str = _f("baked", "how shadows are drawn: 'baked' (the static world's shadows drawn once per world; "
                            "one pass a frame) or 'mujoco' (MuJoCo's shadow passes, every frame); a saved config "
                            "without this field ran with 'mujoco', and so reads a camera without shadows (nothing to "
                            "draw either way)", saved_without="mujoco")
    msaa: bool = _f(False, "4x multisample anti-aliasing (about +15 ms a frame on these CPUs)")

    def __post_init__(self) -> None:
        _check(self.width > 0 and self.height > 0, "camera size must be positive")
        _check(0 < self.hfov_deg < 170, "camera.hfov_deg must be in (0, 170)")
        _check(-89 < self.pitch_deg < 89, "camera.pitch_deg must be in (-89, 89)")
        _check(self.shadow_method in SHADOW_METHODS,
               f"camera.shadow_method must be one of {', '.join(SHADOW_METHODS)}, got {self.shadow_method!r}")
        if not self.shadows:  # the method draws nothing: one value, so that equal images mean equal configs
            object.__setattr__(self, "shadow_method", "mujoco")

    @property
    def baked_shadows(self) -> bool:
        """Shadows drawn once per world (gsmn/world/shadows.py) rather than by MuJoCo's passes every frame."""
        return self.shadows and self.shadow_method == "baked"

    @property
    def focal(self) -> float:
        """Focal length in pixels: f = (W/2) / tan(HFOV/2); square pixels."""
        return (self.width / 2) / math.tan(math.radians(self.hfov_deg) / 2)

    @property
    def vfov_deg(self) -> float:
        return math.degrees(2 * math.atan((self.height / 2) / self.focal))


@dataclass(frozen=True)
class TaskConfig:
    """Instruction sampling, goal placement and the evaluation metric (paper: Data, Evaluation Metric)."""

    min_goal_distance: float = _f(6.0, "an instruction is accepted only if its goal is farther than this "
                                        "from the start (m)")
    max_goal_distance: float = _f(60.0, "... and nearer than this (m); never binds in a 30 m field")
    goal_in_field: bool = _f(True, "also require the goal to lie inside the field (the original rejected "
                                   "such demonstrations, see gsmn.task.instructions)")
    instruction_draws: int = _f(1000, "landmark/side draws tried before an environment is declared unusable")
    # Departure: the original's 100 steps went with a faster drone than the paper's 1.6 m/s. At 1.6 m/s about
    # 20 % of demonstrations (longer than ~32 m, up to ~49 m) cannot be flown in 100 steps, even by the
    # expert; 150 steps cover all of them (the expert needs at most ~146).
    horizon: int = _f(150, "steps per episode (5 Hz); the original used 100 with a faster drone")
    success_radius: float = _f(6.0, "success: stop closer than this to the named landmark's centre (m)")
    seed: int = _f(0, "base seed; the instruction of environment N is drawn from SeedSequence([seed, N, 1])")

    def __post_init__(self) -> None:
        _check(0 <= self.min_goal_distance < self.max_goal_distance,
               f"need 0 <= task.min_goal_distance < task.max_goal_distance, got {self.min_goal_distance}, "
               f"{self.max_goal_distance}")
        _check(self.instruction_draws >= 1, "task.instruction_draws must be >= 1")
        _check(self.horizon >= 1, f"task.horizon must be >= 1, got {self.horizon}")
        _check(self.success_radius > 0, f"task.success_radius must be positive, got {self.success_radius}")


@dataclass(frozen=True)
class ExpertConfig:
    """The demonstration path and the carrot planner that follows it (paper: Data; original code)."""

    # Demonstration path (a point mass attracted to the goal, pushed out of landmark radii).
    takeoff_distance: float = _f(2.4, "straight segment along the start heading before the point mass (m)")
    demo_step: float = _f(0.12, "point-mass step toward the goal (m)")
    target_tolerance: float = _f(0.6, "the point mass has reached the goal within this distance (m)")
    max_demo_steps: int = _f(500, "reject the path if the point mass needs more steps than this")
    waypoint_spacing: float = _f(1.2, "distance between demonstration waypoints along the path (m)")
    # Carrot planner.
    look_ahead: int = _f(12, "the carrot is this many waypoints ahead of the progress (shrinks at the end)")
    progress_window: int = _f(12, "progress is searched this many waypoints ahead of the last progress")
    ramp_waypoints: float = _f(3.0, "forward speed ramps up linearly over the first this many waypoints")
    min_speed: float = _f(0.1, "floor of the normalised forward speed")
    heading_gain: float = _f(0.5, "normalised yaw rate per radian of heading error to the carrot")
    lateral_gain: float = _f(0.1, "normalised yaw rate per metre of lateral offset from the path")
    stop_before_end: int = _f(1, "STOP once progress reaches this many waypoints before the last one")
    stop_radius: float = _f(1.8, "... and only within this distance of the goal (m; inf: progress alone, as the "
                                 "original); off the path, as in DAgger, progress alone can reach it metres away")

    def __post_init__(self) -> None:
        _check(self.takeoff_distance >= 0, "expert.takeoff_distance must be >= 0")
        _check(self.demo_step > 0, "expert.demo_step must be positive")
        _check(self.target_tolerance > 0, "expert.target_tolerance must be positive")
        _check(self.max_demo_steps >= 1, "expert.max_demo_steps must be >= 1")
        _check(self.waypoint_spacing > 0, "expert.waypoint_spacing must be positive")
        _check(self.look_ahead >= 1 and self.progress_window >= 1,
               "expert.look_ahead and expert.progress_window must be >= 1")
        _check(self.ramp_waypoints >= 0, "expert.ramp_waypoints must be >= 0")
        _check(self.stop_radius > 0, f"expert.stop_radius must be positive, got {self.stop_radius}")
        _check(0 <= self.min_speed <= 1, f"expert.min_speed is normalised, must be in [0, 1], got {self.min_speed}")
        _check(self.heading_gain >= 0 and self.lateral_gain >= 0, "expert gains must be >= 0")
        _check(self.stop_before_end >= 0, "expert.stop_before_end must be >= 0")


@dataclass(frozen=True)
class ModelConfig:
    """GSMN and its first-person baselines (paper: Model Architecture, Systems; sizes from the original code).

    The world map covers the field (world.field_size) with map_size x map_size cells; the robot-frame map has
    the same cell size. See docs/model.md for every departure and default."""

    map_size: int = _f(32, "world-frame map cells per side, covering the whole field (0.9375 m cells at 30 m)")
    robot_map_size: int = _f(64, "robot-frame map cells per side, same cell size as the world map")
    feature_channels: int = _f(32, "ResNet feature channels C_f (the semantic map has as many)")
    relevance_channels: int = _f(3, "channels of the relevance map R")
    goal_channels: int = _f(2, "channels of the goal map G")
    # Class counts of the auxiliary heads, here rather than read from the catalogue so that the model imports
    # without the mesh builder; tests/test_model.py checks them against gsmn.world.landmarks and gsmn.task.
    landmark_classes: int = _f(63, "landmark classes the perception and instruction heads tell apart: the models "
                                   "of the landmark catalogue, in its order")
    side_classes: int = _f(4, "sides of a landmark an instruction names (left, right, front, back)")
    word_embedding_dim: int = _f(20, "instruction word embedding size")
    instruction_hidden: int = _f(30, "instruction LSTM hidden size = sentence embedding size")
    leaky_lambda: float = _f(0.2, "leaky-integrator rate of the semantic map (first step: S = F)")
    leaky_relu_slope: float = _f(0.01, "negative slope of every LeakyReLU")
    filter_init_std: float = _f(0.001, "std of the N(0, std) init of the language-to-filter layers")
    # The paper's language-made kernels are the affine map itself (signed); the original squashes them with a sigmoid
    # (all weights positive), which kept our goal maps from following the grounding. Both are L2-normalised
    # (docs/model.md). Checkpoints written before this field existed used the sigmoid (gsmn/model/checkpoint.py).
    filter_activation: str = _f("none", "activation of the language-made filter kernels: none (paper, signed "
                                        "weights) or sigmoid (original code, positive weights)")
    controller_hidden: int = _f(64, "GSMN controller hidden units")
    controller_dropout: float = _f(0.5, "dropout on the flattened controller input")
    # The paper feeds the instruction embedding to the controller, the original code does not (docs/model.md).
    controller_uses_instruction: bool = _f(False, "also feed the sentence embedding to the GSMN controller "
                                                  "(paper: yes; original code: no)")
    fpv_hidden: int = _f(32, "GS-FPV(-MEM) controller hidden units")
    fpv_memory: int = _f(32, "GS-FPV-MEM LSTM size")
    # The original code's -J_ground and -J_goal remove a module, not only its loss (docs/model.md, "Removing a
    # module"): an identity takes the filter's place, and what it passes on is sliced as the original slices it.
    grounding_filter: bool = _f(True, "GSMN's language-conditioned grounding filter (false: the original code's "
                                      "identity in its place; the goal filter and the controller read the semantic "
                                      "map's first relevance_channels channels as the relevance map)")
    goal_filter: bool = _f(True, "GSMN's language-conditioned goal filter (false: the original code's identity in its "
                                 "place; the controller reads the semantic map's first goal_channels channels, in "
                                 "the drone's frame, where the goal map was)")
    pose_noise_std: float = _f(0.0, "std of Gaussian noise on the position (x, y, z) the model sees, fresh every "
                                    "forward (m); the paper's noise experiment uses 0.5")
    pose_noise_yaw_deg: float = _f(0.0, "std of Gaussian noise on the yaw the model sees (deg)")
    channels_last: bool = _f(True, "run the ResNet in channels-last memory format (faster on CPU; same maths), but "
                                   "for training on the CPU, where NCHW is faster")
    inference_bf16: bool = _f(False, "outside training, run the ResNet in bfloat16 autocast (faster on CPUs with "
                                     "AMX; features change by about 2 %, see docs/model.md)")

    def __post_init__(self) -> None:
        _check(self.map_size >= 2 and self.robot_map_size >= 2, "model map sizes must be >= 2")
        for name in ("feature_channels", "relevance_channels", "goal_channels", "landmark_classes", "side_classes",
                     "word_embedding_dim", "instruction_hidden", "controller_hidden", "fpv_hidden", "fpv_memory"):
            _check(getattr(self, name) >= 1, f"model.{name} must be >= 1, got {getattr(self, name)}")
        _check(0 < self.leaky_lambda <= 1, f"model.leaky_lambda must be in (0, 1], got {self.leaky_lambda}")
        _check(0 <= self.controller_dropout < 1, "model.controller_dropout must be in [0, 1)")
        _check(self.filter_init_std >= 0, "model.filter_init_std must be >= 0")
        _check(self.filter_activation in ("sigmoid", "none"),
               f"model.filter_activation must be sigmoid or none, got {self.filter_activation!r}")
        _check(self.pose_noise_std >= 0 and self.pose_noise_yaw_deg >= 0, "model pose noise stds must be >= 0")
        _check(self.feature_channels >= max(self.relevance_channels, self.goal_channels) or
               (self.grounding_filter and self.goal_filter),
               "model.feature_channels must be >= relevance_channels and goal_channels when a filter is removed "
               "(its identity passes on the semantic map's first channels)")


@dataclass(frozen=True)
class LossConfig:
    """The training objective: action loss plus four weighted auxiliaries (paper: Learning, Auxiliary Objectives).

    The switches are the paper's ablations (-J_percept, -J_lang, -J_ground, -J_plan); a switched-off term is
    not computed and contributes exactly zero. Kinds without J_plan ("gsmn-no-plan" and the FPV baselines)
    switch the goal term off themselves."""

    action_weight: float = _f(1.0, "weight of the action loss J_act")
    perception_weight: float = _f(0.1, "weight of the perception objective J_percept")
    language_weight: float = _f(0.1, "weight of the instruction objective J_lang")
    grounding_weight: float = _f(0.1, "weight of the grounding objective J_ground")
    goal_weight: float = _f(0.1, "weight of the planning (goal map) objective J_plan")
    perception: bool = _f(True, "use J_percept (false: the -J_percept ablation)")
    language: bool = _f(True, "use J_lang (false: the -J_lang ablation)")
    grounding: bool = _f(True, "use J_ground (false: the -J_ground ablation)")
    goal: bool = _f(True, "use J_plan (false: the -J_plan ablation)")

    def __post_init__(self) -> None:
        for name in ("action_weight", "perception_weight", "language_weight", "grounding_weight", "goal_weight"):
            _check(getattr(self, name) >= 0, f"loss.{name} must be >= 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class TrainConfig:
    """Supervised learning on expert data (paper: Learning; Hyper-parameters and Implementation Details)."""

    epochs: int = _f(30, "passes over the expert data (the paper trains 30 epochs)")
    batch_size: int = _f(4, "episodes per optimizer step (whole episodes: the semantic map spans them)")
    learning_rate: float = _f(1e-3, "Adam learning rate (paper: 0.001)")
    weight_decay: float = _f(1e-6, "L2 regularisation (paper: gamma = 1e-6; the original code used 1e-7)")
    seed: int = _f(0, "seeds episode order, dropout and sampled negatives, per (epoch, batch): resumes exactly")
    save_every_seconds: float = _f(120.0, "save resumable state at least this often (and after every epoch)")
    threads: int = _f(2, "torch CPU threads")
    device: str = _f("cpu", "torch device training runs on: 'cpu', 'cuda' or 'cuda:N' (rollout workers and "
                     "evaluation stay on the CPU)")
    mirror: float = _f(0.0, "probability that a training episode is mirrored east-west (images flipped, left and "
                       "right swapped; not in the paper: docs/design.md); 0 = off")
    prefetch: int = _f(0, "threads that read (and mirror) the next batches' episodes while a batch trains; 0 = read "
                       "each batch in turn. The same batches either way: it changes speed, not results (worth it on a "
                       "GPU, where reading otherwise takes over half the time)")
    trainable: str = _f("all", "which weights train: 'all', or 'memory' (a GS-FPV-MEM's LSTM and the perceptron's "
                        "weights on its outputs only, everything else frozen; not in the paper: docs/design.md)")

    def __post_init__(self) -> None:
        _check(self.epochs >= 1, f"train.epochs must be at least 1, got {self.epochs}")
        _check(0.0 <= self.mirror <= 1.0,
               f"train.mirror (the share of episodes mirrored) must be a probability in [0, 1], got {self.mirror}")
        _check(self.batch_size >= 1, f"train.batch_size must be at least 1, got {self.batch_size}")
        _check(self.learning_rate > 0, f"train.learning_rate must be positive, got {self.learning_rate}")
        _check(self.weight_decay >= 0, f"train.weight_decay must be >= 0, got {self.weight_decay}")
        _check(self.save_every_seconds >= 0, "train.save_every_seconds must be >= 0")
        _check(self.threads >= 1, f"train.threads must be at least 1, got {self.threads}")
        _check(self.prefetch >= 0, "train.prefetch must be >= 0")
        _check(self.trainable in ("all", "memory"), "train.trainable must be 'all' or 'memory'")
        _check(self.device == "cpu" or re.fullmatch(r"cuda(:\d+)?", self.device) is not None,
               "train.device must be 'cpu', 'cuda' or 'cuda:N'")


@dataclass(frozen=True)
class DaggerConfig:
    """DAggerFM (paper: Algorithm 1; settings from the original code)."""

    iterations: int = _f(150, "DAggerFM iterations, one epoch over the dataset each")
    rollouts_per_iteration: int = _f(24, "N_D: rollouts discarded and collected anew each iteration")
    dataset_size: int = _f(500, "M: rollouts kept in the dataset (discarding uniformly at random)")
    beta0: float = _f(0.92, "the expert acts with probability beta_i = beta0 ** i at each step of iteration i >= 1")
    max_deviation: float = _f(4.5, "a rollout is cut when the drone strays this far from the path (m)")
    workers: int = _f(2, "parallel rollout worker processes")
    split: str = _f("train", "environments rollouts are drawn from")
    mirror_ensemble: bool = _f(False, "the learner flies its rollouts as a test-time mirror ensemble (not in the "
                                      "paper: rollouts then visit the states of the policy that is deployed that way)")

    def __post_init__(self) -> None:
        _check(self.iterations >= 1, f"dagger.iterations must be at least 1, got {self.iterations}")
        _check(self.rollouts_per_iteration >= 1,
               f"dagger.rollouts_per_iteration must be at least 1, got {self.rollouts_per_iteration}")
        _check(self.rollouts_per_iteration <= self.dataset_size,
               f"N_D (dagger.rollouts_per_iteration, {self.rollouts_per_iteration}) cannot exceed M "
               f"(dagger.dataset_size, {self.dataset_size})")
        _check(0 <= self.beta0 <= 1, f"dagger.beta0 must be in [0, 1], got {self.beta0}")
        _check(self.max_deviation > 0, "dagger.max_deviation must be positive")
        _check(self.workers >= 1, f"dagger.workers must be at least 1, got {self.workers}")
        _check(self.split in ("train", "test", "dev"), "dagger.split must be train, test or dev")


@dataclass(frozen=True)
class RunConfig:
    """Everything a run needs, resolved and saved alongside its outputs."""

    world: WorldConfig = field(default_factory=WorldConfig)
    drone: DroneConfig = field(default_factory=DroneConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    expert: ExpertConfig = field(default_factory=ExpertConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    dagger: DaggerConfig = field(default_factory=DaggerConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RunConfig:
        return from_dict(cls, d)


def from_dict(cls: type, d: dict[str, Any]) -> Any:
    """Build a (nested) config dataclass from a plain dict (a saved config); unknown keys are an error. A field the
    dict lacks takes its default, or the value a config saved without it ran with (`saved_without`)."""
    hints = typing.get_type_hints(cls)
    fields = dataclasses.fields(cls)
    unknown = set(d) - {f.name for f in fields}
    if unknown:
        raise ConfigError(f"unknown {cls.__name__} field(s): {sorted(unknown)}")
    kwargs = {f.name: f.metadata["saved_without"] for f in fields if "saved_without" in f.metadata and f.name not in d}
    for name, value in d.items():
        hint = hints[name]
        if dataclasses.is_dataclass(hint) and isinstance(value, dict):
            kwargs[name] = from_dict(hint, value)
        else:
            kwargs[name] = value
    return cls(**kwargs)


def with_overrides(config: Any, overrides: dict[str, str]) -> Any:
    """Return a copy of `config` with dotted-path string overrides applied ("camera.pitch_deg": "30")."""
    for path, text in overrides.items():
        config = _replace_path(config, path.replace("-", "_").split("."), text)
    return config


def _replace_path(obj: Any, parts: list[str], text: str) -> Any:
    names = {f.name for f in dataclasses.fields(obj)}
    if parts[0] not in names:
        raise ConfigError(f"{type(obj).__name__} has no field {parts[0]!r}; fields: {sorted(names)}")
    current = getattr(obj, parts[0])
    if len(parts) > 1:
        return dataclasses.replace(obj, **{parts[0]: _replace_path(current, parts[1:], text)})
    hint = typing.get_type_hints(type(obj))[parts[0]]
    return dataclasses.replace(obj, **{parts[0]: parse_value(hint, text)})


def parse_value(hint: Any, text: str) -> Any:
    """Parse a command-line string into a value of the annotated type."""
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if text.lower() in ("none", "null"):
            return None
        hint = args[0]
    if hint is bool:
        if text.lower() in ("1", "true", "yes", "on"):
            return True
        if text.lower() in ("0", "false", "no", "off"):
            return False
        raise ConfigError(f"expected a boolean, got {text!r}")
    try:
        return hint(text)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"cannot read {text!r} as {getattr(hint, '__name__', hint)}") from e


def leaf_fields(cls: type, prefix: str = "") -> list[tuple[str, Any, dataclasses.Field]]:
    """(dotted path, type, field) for every non-dataclass field of a nested config class."""
    out = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        if dataclasses.is_dataclass(hint):
            out.extend(leaf_fields(hint, f"{prefix}{f.name}."))
        else:
            out.append((f"{prefix}{f.name}", hint, f))
    return out


def preset(name: str) -> RunConfig:
    """A named preset: `paper` or `tiny`."""
    if name == "paper":
        return RunConfig()
    if name == "tiny":
        # Same world and dynamics; cheaper images so tests and CI stay fast.
        return RunConfig(camera=CameraConfig(shadows=False, msaa=False))
    raise ConfigError(f"unknown preset {name!r}; choose from {PRESETS}")


PRESETS = ("paper", "tiny")


@dataclass(frozen=True)
class FineTunePreset:
    """The size of a DAggerFM fine-tuning run, as the dashboard launches one (app.jobs.settings): what it takes from
    `dagger` (iterations, rollouts_per_iteration, dataset_size, beta0, workers) and `train` (learning_rate,
    batch_size, threads, mirror), the rollouts' horizon, and how many dev episodes it validates on. A field not
    given is its class's default; the rest of the run's configuration is the server's."""

    dev_episodes: int  # expert episodes of the dev split validated on after every iteration
    dagger: DaggerConfig = field(default_factory=DaggerConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    horizon: int | None = None  # steps per rollout (task.horizon); None: the configuration's own

    def __post_init__(self) -> None:
        _check(self.dev_episodes >= 1, f"dev_episodes must be at least 1, got {self.dev_episodes}")
        _check(self.horizon is None or self.horizon >= 1, f"horizon must be >= 1 or None, got {self.horizon}")


FINE_TUNE_PRESETS: dict[str, FineTunePreset] = {
    # a minute or two on a busy 2-core machine: 2 iterations of 2 short rollouts on a dataset of 4
    "tiny": FineTunePreset(
        dagger=DaggerConfig(iterations=2, rollouts_per_iteration=2, dataset_size=4, beta0=0.5, workers=1),
        train=TrainConfig(batch_size=2, threads=1), horizon=30, dev_episodes=2),
    # some tens of minutes: a first look at what fine-tuning on failures does
    "small": FineTunePreset(
        dagger=DaggerConfig(iterations=10, rollouts_per_iteration=8, dataset_size=40, workers=1),
        train=TrainConfig(threads=1), dev_episodes=8),
    # the paper's (DaggerConfig's and TrainConfig's defaults), training on one torch thread beside the rollout workers
    "paper": FineTunePreset(train=TrainConfig(threads=1), dev_episodes=30),
}
