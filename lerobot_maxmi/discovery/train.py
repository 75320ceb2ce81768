"""Train KSL-Net with the MaxMI criterion and localize key frames in episodes."""

import logging
from dataclasses import asdict, dataclass, field
from operator import attrgetter

import torch
from accelerate import Accelerator, PartialState
from torch import Tensor
from tqdm import tqdm

from lerobot_maxmi.cpu_memory import reuse_freed_memory
from lerobot_maxmi.discovery.ksl_net import CONCEPT_STARTS, KSLNet, soft_argmax, stack_resampled
from lerobot_maxmi.discovery.losses import diversity_loss, maxmi_loss, ordering_loss, released_maxmi_loss
from lerobot_maxmi.discovery.nms import shared_concepts
from lerobot_maxmi.discovery.processor import MaxmiDiscoveryStep
from lerobot_maxmi.mi import ESTIMATORS, STATE_MI_MODES, load_estimator
from lerobot_maxmi.mi.estimators import resolve_device
from lerobot_maxmi.mi.normalize import MIN_SAMPLES

OBJECTIVES = ("paper", "released")
# Training cost grows linearly with T; 64 steps still place a key state within 1/63 of the episode,
# well inside the 5% tolerance it is scored at, and keep 500 long episodes trainable on a laptop.
DEFAULT_MAX_RESAMPLE_LENGTH = 64


@dataclass
class KSLNetArchitecture:
    """Layer sizes of `KSLNet`."""

    embed_dim: int = 10
    encoder_dims: tuple[int, ...] = (256, 256, 256)
    head_dims: tuple[int, ...] = (256, 128)
    # Where the concepts start: "paper" (where the untrained head puts them) or "spread" (one per
    # K-th of the episode; ours, so not the default; docs/discovery.md, "Which flags for which data").
    concept_start: str = "paper"


@dataclass
class DiscoveryConfig:
    """How key states are discovered. Defaults follow the paper (objective="paper")."""

    num_concepts: int = 10  # K
    # T; None = the shortest episode's length, at most DEFAULT_MAX_RESAMPLE_LENGTH.
    resample_length: int | None = None
    delta_t: float = 2.0  # Δt, in resampled steps
    diversity_weight: float = 1.0  # λ
    mi_weight: float = 1.0  # weight of the MaxMI term (0 = diversity only, the paper's Table 5 ablation)
    # "paper": −Σ_k MI per concept + λ·pairwise diversity. "released": the authors' code
    # (one pooled MI ×4, extrapolated s_t−Δt, ordering loss).
    objective: str = "paper"
    estimator: str = "infonet"
    state_mi_mode: str = "per_dim"
    lr: float = 1e-3
    steps: int = 1000
    batch_size: int = 64
    seed: int = 0
    device: str = "auto"
    nms_radius: float = 0.05  # fraction of the episode length
    append_final_frame: bool = True
    # A saved localizer (directory or hub repo id) to annotate with instead of training one.
    pretrained_path: str | None = None
    model: KSLNetArchitecture = field(default_factory=KSLNetArchitecture)

    def __post_init__(self):
        if self.num_concepts < 1:
            raise ValueError(f"num_concepts must be >= 1, got {self.num_concepts}")
        choices = {
            "objective": OBJECTIVES,
            "estimator": tuple(ESTIMATORS),
            "state_mi_mode": STATE_MI_MODES,
            "model.concept_start": CONCEPT_STARTS,
        }
        for name, valid in choices.items():
            if (value := attrgetter(name)(self)) not in valid:
                raise ValueError(f"unknown {name} {value!r}; choose one of {', '.join(valid)}")


def check_episodes(episodes: list[Tensor], num_concepts: int) -> None:
    if not episodes:
        raise ValueError("no episodes to discover key states in")
    for i, states in enumerate(episodes):
        if states.ndim != 2:
            raise ValueError(
                f"episode {i}: states must be (frames, state_dim), got shape {tuple(states.shape)}"
            )
        if len(states) < max(num_concepts, 2):
            raise ValueError(
                f"episode {i} has {len(states)} frames, fewer than the {num_concepts} key states asked for; "
                "lower --discovery.num_concepts or drop short episodes"
            )
        if not torch.isfinite(states).all():
            raise ValueError(f"episode {i} has NaN or inf states; clean the dataset before discovery")


def discovery_objective(net: KSLNet, states: Tensor, estimator, cfg: DiscoveryConfig) -> dict[str, Tensor]:
    t_hat = soft_argmax(net(states))
    if cfg.objective == "released":
        mi_term = released_maxmi_loss(states, t_hat, estimator, cfg.state_mi_mode)
        spread_term = ordering_loss(t_hat)
    else:
        mi_term, _ = maxmi_loss(states, t_hat, cfg.delta_t, estimator, cfg.state_mi_mode)
        spread_term = diversity_loss(t_hat)
    loss = cfg.mi_weight * mi_term + cfg.diversity_weight * spread_term
    return {"loss": loss, "mi": -mi_term, "diversity": spread_term}


def cpu_process_group() -> bool:
    """Without a GPU, accelerate forms a multi-process (gloo) group only when told to use the CPU."""
    return not torch.cuda.is_available()


def make_accelerator() -> Accelerator:
    """A no-op in one process; data-parallel (DDP) under `accelerate launch` / torchrun, where each process
    draws its own batches and gradients are averaged. We place tensors ourselves, so that one process
    keeps --discovery.device."""
    return Accelerator(cpu=cpu_process_group(), device_placement=False)


def train_localizer(episodes: list[Tensor], cfg: DiscoveryConfig) -> KSLNet:
    """Fit KSL-Net to the episodes' (frames, state_dim) state sequences."""
    check_episodes(episodes, cfg.num_concepts)
    if min(cfg.batch_size, len(episodes)) < MIN_SAMPLES:
        raise ValueError(
            f"MaxMI estimates MI across episodes and needs batches of at least {MIN_SAMPLES}; got "
            f"{len(episodes)} episodes and --discovery.batch_size={cfg.batch_size}"
        )
    torch.manual_seed(cfg.seed)
    accelerator = make_accelerator()
    # Launched processes use the device the launcher gives each of them.
    device = resolve_device(cfg.device) if accelerator.num_processes == 1 else accelerator.device
    reuse_freed_memory(device)
    length = cfg.resample_length or min(DEFAULT_MAX_RESAMPLE_LENGTH, *(len(states) for states in episodes))
    data = stack_resampled(episodes, length).to(device)
    net = KSLNet(data.shape[-1], length, cfg.num_concepts, **asdict(cfg.model)).to(device)
    frames = data.flatten(0, 1)
    net.set_state_statistics(frames.mean(0), frames.std(0))
    estimator = load_estimator(cfg.estimator, device=device)
    optimizer = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    net, optimizer = accelerator.prepare(net, optimizer)
    generator = torch.Generator().manual_seed(cfg.seed + accelerator.process_index)
    batch_size = min(cfg.batch_size, len(episodes))
    progress = tqdm(range(cfg.steps), desc="discover key states", disable=not accelerator.is_main_process)
    for _ in progress:
        batch = data[torch.randperm(len(data), generator=generator)[:batch_size].to(device)]
        terms = discovery_objective(net, batch, estimator, cfg)
        optimizer.zero_grad(set_to_none=True)
        accelerator.backward(terms["loss"])
        optimizer.step()
        progress.set_postfix({k: f"{v.item():.3f}" for k, v in terms.items()})
    logging.info(
        "trained KSL-Net on %d episodes resampled to %d steps (%d process(es), %d torch thread(s) each)",
        len(episodes),
        length,
        accelerator.num_processes,
        torch.get_num_threads(),
    )
    return accelerator.unwrap_model(net).eval()


def training_record(cfg: DiscoveryConfig) -> dict:
    """What repeats a training run exactly. The process count sets the batches; the torch thread count
    sets CPU float rounding, which training amplifies into different key frames (docs/RESULTS.md)."""
    return {
        "discovery": asdict(cfg),
        "torch_version": torch.__version__,
        "processes": PartialState(cpu=cpu_process_group()).num_processes,
        "torch_threads": torch.get_num_threads(),
    }


def collapse_warning(kept: int, num_concepts: int) -> str | None:
    """What to tell the user when NMS kept none of the concepts, or one of several, else None."""
    if kept > 1 or kept == num_concepts:
        return None
    if kept == 0:
        where = "at the final frame, so no concept is kept and the key states are the last state's"
    else:
        where = "within --discovery.nms_radius of one another, so one key state is kept"
    if num_concepts == 1:
        # One concept has no diversity term to push it off the end; only more concepts can.
        return f"the one concept sits {where}. Ask for more with --discovery.num_concepts."
    return (
        f"all {num_concepts} concepts sit {where}: the objective collapsed. Concepts collapse without "
        "the diversity term (--discovery.diversity_weight=0) and under --discovery.objective=released; "
        "a larger --discovery.diversity_weight spreads them."
    )


def fit_localizer(episodes: list[Tensor], cfg: DiscoveryConfig) -> MaxmiDiscoveryStep:
    """Train KSL-Net, keep the concepts that are distinct dataset-wide, and wrap both as a processor step.

    Each concept's typical position is its median t̂ over the episodes (a fraction of the
    episode); NMS on those positions, scored by mean confidence, drops duplicate concepts once
    for the whole dataset, so every episode gets the same K_out = kept + final key states.
    """
    net = train_localizer(episodes, cfg)
    t_hat, confidence = net.locate(episodes)
    fractions = (t_hat / (net.length - 1)).median(dim=0).values
    concepts = shared_concepts(
        fractions.tolist(), confidence.mean(dim=0).tolist(), cfg.nms_radius, cfg.append_final_frame
    )
    logging.info("kept %d of %d concepts dataset-wide: %s", len(concepts), cfg.num_concepts, concepts)
    if warning := collapse_warning(len(concepts), cfg.num_concepts):
        logging.warning(warning)
    return MaxmiDiscoveryStep.from_net(net, concepts, cfg.append_final_frame, **asdict(cfg.model))
