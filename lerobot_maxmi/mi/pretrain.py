"""`lerobot-maxmi-pretrain-mi`: pretrain InfoNet on synthetic 2-D Gaussian mixtures.

Each step draws a batch of random mixtures, N input samples from each (N log-uniform in
[min_samples, max_samples]), a disjoint set of points on which the critic's DV bound is
maximized (so the critic cannot overfit the points it was computed from), and Monte-Carlo
ground-truth MI for the regression head. Steps are seeded by (seed, step), so a resumed run
sees exactly the batches an uninterrupted one would.

    lerobot-maxmi-pretrain-mi --output_dir=outputs/infonet --steps=20000
    lerobot-maxmi-pretrain-mi --output_dir=outputs/infonet --steps=30000 --resume=true

`--init_from=<InfoNet directory or repo id>` starts from saved weights. With
`--trainable=regression_head` a new regression head trains on its frozen encoder and critic (which
stay bit-identical); with `--trainable=all` the whole network, head included, is fine-tuned.
"""

import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import draccus
import torch
from huggingface_hub import hf_hub_download
from huggingface_hub.constants import SAFETENSORS_SINGLE_FILE
from lerobot.utils.utils import init_logging
from safetensors.torch import load_file, load_model
from tqdm import tqdm

from lerobot_maxmi.cpu_memory import reuse_freed_memory
from lerobot_maxmi.mi.estimators import resolve_device
from lerobot_maxmi.mi.ground_truth import random_gaussian_mixtures
from lerobot_maxmi.mi.infonet import InfoNet, InfoNetConfig, donsker_varadhan
from lerobot_maxmi.mi.normalize import hard_rank

CHECKPOINT_DIR = "checkpoint"
FINAL_DIR = "final"
TRAINING_STATE = "training_state.pt"
TRAINABLE = ("all", "regression_head")


@dataclass
class PretrainMIConfig:
    output_dir: Path = Path("outputs/infonet")
    steps: int = 12_000
    batch_size: int = 64
    lr: float = 1e-3
    warmup_steps: int = 300
    grad_clip_norm: float = 1.0
    # Input set sizes are drawn log-uniformly in [min_samples, max_samples].
    min_samples: int = 64
    max_samples: int = 1024
    # Held-out points per mixture on which the critic's DV bound is scored.
    critic_samples: int = 512
    # Samples per mixture for the Monte-Carlo MI label of the regression head.
    mc_samples: int = 1024
    max_components: int = 20
    # Share of batches drawn as single bivariate Gaussians instead of mixtures. Mixtures rarely have MI
    # near 0, and a head trained on them alone reads weak dependence as ~0.05 nats too much.
    gaussian_share: float = 0.0
    regression_weight: float = 1.0
    # "all", or "regression_head": only the regression head learns; needs init_from.
    trainable: str = "all"
    # An InfoNet (directory or hub repo id) that starts the run: all of it for trainable="all", its
    # encoder and critic for "regression_head" (whose head starts fresh).
    init_from: str | None = None
    seed: int = 0
    device: str = "auto"
    save_freq: int = 500
    resume: bool = False
    model: InfoNetConfig = field(default_factory=InfoNetConfig)

    def __post_init__(self):
        if self.trainable not in TRAINABLE:
            raise ValueError(f"unknown trainable {self.trainable!r}; choose one of {', '.join(TRAINABLE)}")
        if not 0 <= self.gaussian_share <= 1:
            raise ValueError(f"gaussian_share is a fraction of batches in [0, 1]; got {self.gaussian_share}")
        if self.trainable == "regression_head" and self.init_from is None:
            raise ValueError(
                "--trainable=regression_head trains on a frozen encoder: pass --init_from=<InfoNet>"
            )


def draw_batch(cfg: PretrainMIConfig, step: int) -> dict[str, torch.Tensor]:
    """Input copula samples, held-out critic points and MI labels for one step."""
    generator = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)
    log_n = math.log(cfg.min_samples) + torch.rand(1, generator=generator).item() * math.log(
        cfg.max_samples / cfg.min_samples
    )
    n = round(math.exp(log_n))
    # Without a Gaussian share nothing is drawn here, so such runs see the batches they always did.
    single = cfg.gaussian_share > 0 and torch.rand(1, generator=generator).item() < cfg.gaussian_share
    mixtures = random_gaussian_mixtures(
        cfg.batch_size, 1 if single else cfg.max_components, generator=generator, dtype=torch.float32
    )
    points = mixtures.sample(n + cfg.critic_samples + cfg.mc_samples, generator)
    inputs, held_out, mc = points.split([n, cfg.critic_samples, cfg.mc_samples], dim=1)
    u, v = hard_rank(inputs[..., 0]), hard_rank(inputs[..., 1])
    hu, hv = hard_rank(held_out[..., 0]), hard_rank(held_out[..., 1])
    mi = mixtures.pointwise_mi(mc).mean(dim=1)
    return {k: t.float() for k, t in dict(u=u, v=v, held_u=hu, held_v=hv, mi=mi).items()}


def training_losses(model: InfoNet, batch: dict[str, torch.Tensor], regression_weight: float) -> dict:
    """−DV on held-out points (the critic) + weight · |regression − MI| (L1: MAE is what we are scored on).

    The regression head reads the critic's estimate but does not train the critic through it.
    """
    u, v = batch["u"], batch["v"]
    latents = model.encode(u, v)
    table = model.critic_table(latents)
    held_out_dv = donsker_varadhan(table, batch["held_u"], batch["held_v"])
    regression_error = (model.regression(latents, u, v, table.detach()) - batch["mi"]).abs().mean()
    with torch.no_grad():
        critic_error = (donsker_varadhan(table, u, v) - batch["mi"]).abs().mean()
    return {
        "loss": -held_out_dv.mean() + regression_weight * regression_error,
        "dv": held_out_dv.mean().detach(),
        "critic_mae": critic_error,
        "regression_mae": regression_error.detach(),
    }


def load_initial_weights(model: InfoNet, source: str, trainable: str) -> None:
    """Copy a saved InfoNet's tensors (local directory or hub repo id); all but the head for a new head."""
    local = Path(source) / SAFETENSORS_SINGLE_FILE
    path = local if local.exists() else hf_hub_download(source, SAFETENSORS_SINGLE_FILE)

    def kept(name: str) -> bool:
        # "regression" also skips the head of files saved before it was rebuilt (`regression_out.*`).
        return trainable == "all" or not name.startswith("regression")

    state = {name: t for name, t in load_file(path).items() if kept(name)}
    expected = {name: t.shape for name, t in model.state_dict().items() if kept(name)}
    if {name: t.shape for name, t in state.items()} != expected:
        raise ValueError(
            f"{source} holds an InfoNet of other sizes than --model.*; pass its config.json values"
        )
    model.load_state_dict(state, strict=False)


def select_trainable(model: InfoNet, trainable: str) -> list[torch.nn.Parameter]:
    if trainable == "regression_head":
        model.requires_grad_(False)
        model.regression_head.requires_grad_(True)
    return [p for p in model.parameters() if p.requires_grad]


def warmup_cosine(warmup_steps: int, total_steps: int):
    def factor(step: int) -> float:
        if step < warmup_steps:
            return (step + 1) / warmup_steps
        progress = (step - warmup_steps) / max(1, total_steps - warmup_steps)
        return 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(1.0, progress)))

    return factor


def save(model, optimizer, scheduler, step: int, cfg: PretrainMIConfig, directory: Path) -> None:
    model.save_pretrained(directory)
    torch.save(
        {"optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(), "step": step},
        directory / TRAINING_STATE,
    )
    (directory / "pretrain_config.json").write_text(json.dumps(asdict(cfg), default=str, indent=2))


def pretrain(cfg: PretrainMIConfig) -> Path:
    """Train (or resume) and return the directory holding the final weights."""
    torch.manual_seed(cfg.seed)
    device = resolve_device(cfg.device)
    reuse_freed_memory(device)
    checkpoint = cfg.output_dir / CHECKPOINT_DIR
    if checkpoint.exists() and not cfg.resume:
        raise FileExistsError(
            f"{checkpoint} exists; pass --resume=true to continue it or choose another --output_dir"
        )
    resuming = cfg.resume and checkpoint.exists()
    model = InfoNet(**asdict(cfg.model)).to(device)
    if resuming:
        load_model(model, checkpoint / SAFETENSORS_SINGLE_FILE, device=str(device))
    elif cfg.init_from:
        load_initial_weights(model, cfg.init_from, cfg.trainable)
    parameters = select_trainable(model, cfg.trainable)
    optimizer = torch.optim.AdamW(parameters, lr=cfg.lr, weight_decay=1e-4)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, warmup_cosine(cfg.warmup_steps, cfg.steps))
    start = 0
    if resuming:
        state = torch.load(checkpoint / TRAINING_STATE, map_location=device)
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        start = state["step"]
        logging.info("resuming from step %d", start)
    model.train()
    progress = tqdm(range(start, cfg.steps), initial=start, total=cfg.steps, desc="pretrain InfoNet")
    began = time.perf_counter()
    for step in progress:
        batch = {k: t.to(device) for k, t in draw_batch(cfg, step).items()}
        losses = training_losses(model, batch, cfg.regression_weight)
        optimizer.zero_grad(set_to_none=True)
        losses["loss"].backward()
        torch.nn.utils.clip_grad_norm_(parameters, cfg.grad_clip_norm)
        optimizer.step()
        scheduler.step()
        progress.set_postfix({k: f"{v.item():.3f}" for k, v in losses.items() if k != "loss"})
        if (step + 1) % cfg.save_freq == 0 or step + 1 == cfg.steps:
            save(model, optimizer, scheduler, step + 1, cfg, checkpoint)
    final = cfg.output_dir / FINAL_DIR
    model.save_pretrained(final)
    logging.info("saved %s after %.0f s", final, time.perf_counter() - began)
    return final


@draccus.wrap()
def run(cfg: PretrainMIConfig) -> None:
    pretrain(cfg)


def main() -> None:
    init_logging()
    run()


if __name__ == "__main__":
    main()
