"""A trained model as a `gsmn.task.rollout.Policy` (paper: Model Architecture, "at each step j, the network takes
the agent context (instruction, image, pose) and predicts the next action").

The policy object holds the runtime state, the network stays pure: the sentence embedding and the language
filters' kernels (made once per episode), the carried state (GSMN: the semantic map; GS-FPV-MEM: the LSTM
state) and the last step's outputs record (`last_outputs`, a GSMNOutputs or FPVOutputs with B = T = 1) for the
dashboard. Actions come out in SI units: v * 1.6 m/s, omega * 2.44 rad/s (the drone's limits), STOP when
sigmoid(stop_logit) > 0.5.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from gsmn.config import RunConfig
from gsmn.model.filters import InstructionKernels
from gsmn.model.gsmn import GSMN, GroundingOutputs
from gsmn.model.models import Model, Outputs
from gsmn.model.vocabulary import Vocabulary
from gsmn.task.mirror import mirror_observation, mirror_task
from gsmn.task.rollout import PolicyAction, Task
from gsmn.world.env import Observation


class ModelPolicy:
    """Any model from `build_model` as a policy. `reset` puts the model in eval mode."""

    needs_images = True

    def __init__(self, model: Model, vocabulary: Vocabulary, config: RunConfig | None = None, name: str | None = None):
        self.model = model
        self.vocabulary = vocabulary
        self.config = config or model.config
        self.name = name or model.kind
        self.sentence_embedding: torch.Tensor | None = None
        self.kernels: InstructionKernels | None = None
        self.state = None
        self.last_outputs: Outputs | None = None
        self.generator = torch.Generator()
        self.substitute_maker = None  # what makes an episode's map substitute (`intervene`), or None
        self.substitute = None  # this episode's, made from its task

    def intervene(self, maker, task: Task | None = None) -> None:
        """Fly with a map intervention: `maker(task)` makes the episode's substitute
        (`gsmn.analysis.intervention.InterventionMaker`); None stops intervening. With `task`, the substitute
        starts now, mid-episode (a fork); otherwise at the next `reset`."""
        self.substitute_maker = maker
        self.substitute = maker(task) if maker is not None and task is not None else None

    def reset(self, task: Task) -> None:
        self.model.eval()
        self.generator.manual_seed(task.world.env_id)  # pose noise, when configured, repeats per environment
        self.sentence_embedding = self.embed(task.instruction.text)
        with torch.inference_mode():
            self.kernels = self.model.instruction_kernels(self.sentence_embedding)
        self.state = None
        self.last_outputs = None
        self.substitute = self.substitute_maker(task) if self.substitute_maker is not None else None

    def carried(self) -> tuple:
        """What this policy carries from one step to the next, apart from what its instruction makes at `reset`
        (the embedding and kernels): the semantic map (or LSTM state) and the pose-noise generator's state.
        `restore` puts it back, so the policy acts on from there as it did (a fork, `gsmn.task.fork`)."""
        state = None if self.state is None else _clone(self.state)
        return state, self.generator.get_state()

    def restore(self, carried: tuple) -> None:
        state, generator = carried
        self.state = None if state is None else _clone(state)
        self.generator.set_state(generator)

    def embed(self, text: str) -> torch.Tensor:
        """The sentence embedding (1, E) of an instruction."""
        ids = self.vocabulary.encode(text)
        with torch.inference_mode():
            return self.model.encode_instruction(torch.tensor([ids]), torch.tensor([len(ids)]))

    def act(self, obs: Observation) -> PolicyAction:
        if self.sentence_embedding is None:
            raise RuntimeError("call reset(task) before act")
        if obs.image is None:
            raise ValueError("this policy needs camera images; make the Env with render=True")
        with torch.inference_mode():
            image = torch.from_numpy(obs.image)[None]  # (1, H, W, 3)
            T_world_camera = torch.as_tensor(obs.T_world_camera, dtype=torch.float32)[None]
            K = torch.as_tensor(obs.K, dtype=torch.float32)[None]
            p = obs.pose.position
            poses = torch.tensor([[p[0], p[1], obs.pose.yaw]], dtype=torch.float32)
            extra = {"substitute": self.substitute} if self.substitute is not None else {}
            outputs, self.state = self.model.step(image, T_world_camera, K, poses, self.sentence_embedding,
                                                  self.state, self.generator, self.kernels, **extra)
        self.last_outputs = outputs
        drone = self.config.drone
        return PolicyAction(forward_velocity=float(outputs.v[0, 0]) * drone.max_forward_velocity,
                            yaw_rate=float(outputs.omega[0, 0]) * drone.max_yaw_rate,
                            stop=bool(outputs.stop_logit[0, 0] > 0),  # sigmoid(logit) > 0.5
                            stop_probability=float(torch.sigmoid(outputs.stop_logit[0, 0])))

    def counterfactual(self, text: str) -> GroundingOutputs:
        """Ground another instruction on the current semantic map at the current pose (GSMN only), without
        changing the episode: the dashboard's counterfactual mode."""
        if not isinstance(self.model, GSMN):
            raise TypeError(f"counterfactual grounding needs a semantic map; {self.model.kind!r} has none")
        if self.last_outputs is None:
            raise RuntimeError("no semantic map yet: act at least once")
        with torch.inference_mode():
            return self.model.ground(self.last_outputs.semantic_map_w[:, 0], self.last_outputs.poses[:, 0],
                                     self.embed(text))


GSMNPolicy = ModelPolicy


def _clone(state):
    """A copy of a carried state: a tensor or a tuple of tensors (an LSTM's)."""
    if isinstance(state, torch.Tensor):
        return state.clone()
    return type(state)(_clone(s) for s in state)


class Ensemble:
    """A test-time ensemble of models of one kind (not in the paper; docs/design.md, "Mirror ensemble" and
    "Test-time ensembles of checkpoints").

    Each member is a `ModelPolicy` with its own runtime state (its own semantic map) flying the same episode.
    With `mirror`, every model flies a second time on the east-west mirror image of what the drone observes
    (`gsmn.task.mirror`: the image flipped, the pose and camera reflected, "left" and "right" swapped in the
    instruction). The members' actions are averaged, a mirrored member's yaw rate negated back: v = mean v_i,
    omega = mean s_i omega_i (s_i = -1 mirrored, +1 not), STOP when the mean of the stop probabilities is above
    0.5. Members that are not the same function (weights from other iterations, or a model that is not perfectly
    mirror-symmetric, which none is) make errors that partly cancel. The compute per step is the members'.

    `last_outputs` and `counterfactual` are the first model's unmirrored copy's (what the dashboard shows)."""

    needs_images = True

    def __init__(self, policies: Sequence[ModelPolicy], mirror: bool = False):
        if not policies:
            raise ValueError("an ensemble needs at least one model")
        kinds = {p.model.kind for p in policies}
        if len(kinds) > 1:
            raise ValueError(f"an ensemble's models must be of one kind, not {sorted(kinds)}")
        self.policy = policies[0]
        self.members: list[tuple[ModelPolicy, bool]] = [(p, False) for p in policies]
        if mirror:
            self.members += [(ModelPolicy(p.model, p.vocabulary, p.config, p.name), True) for p in policies]
        self.mirror = mirror
        self.name = self.policy.name
        self.model, self.config = self.policy.model, self.policy.config  # what TraceRecorder reads
        self.field_size: float | None = None

    @property
    def last_outputs(self) -> Outputs | None:
        return self.policy.last_outputs

    def reset(self, task: Task) -> None:
        mirrored = mirror_task(task) if self.mirror else None
        for policy, m in self.members:
            policy.reset(mirrored if m else task)
        self.field_size = task.world.field_size

    def act(self, obs: Observation) -> PolicyAction:
        if self.field_size is None:
            raise RuntimeError("call reset(task) before act")
        mirrored = mirror_observation(obs, self.field_size) if self.mirror else None
        v = omega = 0.0
        p_stops = []
        for policy, m in self.members:
            a = policy.act(mirrored if m else obs)
            v += a.forward_velocity
            omega += -a.yaw_rate if m else a.yaw_rate
            p_stops.append(a.stop_probability)
        n = len(self.members)
        p_stop = sum(p_stops) / n
        return PolicyAction(forward_velocity=v / n, yaw_rate=omega / n, stop=p_stop > 0.5, stop_probability=p_stop,
                            member_stop_probabilities=tuple(p_stops))

    def carried(self) -> tuple:
        """Every member's carried state, in member order (`ModelPolicy.carried`)."""
        return tuple(p.carried() for p, _ in self.members)

    def restore(self, carried: tuple) -> None:
        for (p, _), c in zip(self.members, carried, strict=True):
            p.restore(c)

    def counterfactual(self, text: str) -> GroundingOutputs:
        return self.policy.counterfactual(text)


class MirrorEnsemble(Ensemble):
    """One model flown as a test-time mirror ensemble: on the observation and on its mirror image, the two actions
    averaged (v = (v + v') / 2, omega = (omega - omega') / 2)."""

    def __init__(self, policy: ModelPolicy):
        super().__init__([policy], mirror=True)
