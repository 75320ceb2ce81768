"""CoTPC speed on this machine's CPU at the paper's size; prints a markdown table.

    .venv/bin/python benchmarks/cotpc_speed.py                     # defaults: PickCube-sized, batch 256
    .venv/bin/python benchmarks/cotpc_speed.py --train_steps=3 --rollout_steps=100

Measures select_action latency (one environment, a full 60-step history after warm-up), training
throughput (forward + backward + AdamW step on LeRobot-shaped windows) and the process's peak RSS
after the training steps (an upper bound for one step: it includes Python, torch and the model).
Targets: latency <= 5 ms, peak RSS <= 8 GB.
"""

import argparse
import os
import platform
import resource
import statistics
import time

import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_STATE

from lerobot_maxmi.policies.cotpc.configuration_cotpc import OBS_KEY_STATES, CotpcConfig
from lerobot_maxmi.policies.cotpc.modeling_cotpc import CotpcPolicy


def make_policy(args) -> CotpcPolicy:
    input_features = {OBS_STATE: PolicyFeature(FeatureType.STATE, (args.state_dim,))}
    if args.key_states:
        shape = (args.key_states * args.state_dim,)
        input_features[OBS_KEY_STATES] = PolicyFeature(FeatureType.STATE, shape)
    config = CotpcConfig(
        device="cpu",
        fps=20,
        input_features=input_features,
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (args.action_dim,))},
    )
    return CotpcPolicy(config)


def select_action_latency_ms(policy: CotpcPolicy, args) -> list[float]:
    """Per-step latency of select_action over a rollout, after filling the history."""
    policy.reset()
    observation = {OBS_STATE: torch.randn(1, args.state_dim)}
    for _ in range(policy.config.context_length):
        policy.select_action(observation)
    latencies = []
    for _ in range(args.rollout_steps):
        start = time.perf_counter()
        policy.select_action(observation)
        latencies.append(1000 * (time.perf_counter() - start))
    return latencies


def training_batch(policy: CotpcPolicy, args) -> dict:
    length, batch_size = policy.config.context_length, args.batch_size
    padding = torch.randint(0, length, (batch_size,))
    is_pad = torch.arange(length)[None] < padding[:, None]
    batch = {
        OBS_STATE: torch.randn(batch_size, length, args.state_dim),
        ACTION: torch.randn(batch_size, length, args.action_dim),
        f"{OBS_STATE}_is_pad": is_pad,
        f"{ACTION}_is_pad": is_pad,
        "timestamp": torch.rand(batch_size) * 10,
    }
    if args.key_states:
        batch[OBS_KEY_STATES] = torch.randn(batch_size, length, args.key_states * args.state_dim)
    return batch


def training_samples_per_s(policy: CotpcPolicy, args) -> float:
    optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())
    batch = training_batch(policy, args)
    policy.train()

    def step():
        loss, _ = policy.forward(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    step()  # warm-up: allocator and optimizer state
    start = time.perf_counter()
    for _ in range(args.train_steps):
        step()
    return args.batch_size * args.train_steps / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--state_dim", type=int, default=51, help="PickCube (ManiSkill2 state obs)")
    parser.add_argument("--action_dim", type=int, default=8)
    parser.add_argument("--key_states", type=int, default=6, help="K (MaxMI: 5 discovered + final)")
    parser.add_argument("--batch_size", type=int, default=256)
    parser.add_argument("--train_steps", type=int, default=10)
    parser.add_argument("--rollout_steps", type=int, default=300)
    parser.add_argument("--threads", type=int, help="torch threads (default: torch's choice)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    policy = make_policy(args)
    latencies = select_action_latency_ms(policy, args)
    throughput = training_samples_per_s(policy, args)
    peak_rss_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # Linux reports KiB

    parameters = sum(p.numel() for p in policy.parameters())
    print(
        f"\nCoTPC {parameters / 1e6:.2f} M parameters, state {args.state_dim}, action {args.action_dim}, "
        f"K={args.key_states}, context {policy.config.context_length}; torch threads "
        f"{torch.get_num_threads()}; {platform.machine()} {os.cpu_count()} cores\n"
    )
    print("| metric | value | target |")
    print("|---|---|---|")
    print(
        f"| select_action latency, batch 1 (median / p90) | {statistics.median(latencies):.2f} / "
        f"{statistics.quantiles(latencies, n=10)[-1]:.2f} ms | <= 5 ms |"
    )
    print(f"| training throughput, batch {args.batch_size} | {throughput:.0f} samples/s | |")
    print(f"| peak RSS after training steps, batch {args.batch_size} | {peak_rss_gb:.2f} GB | <= 8 GB |")


if __name__ == "__main__":
    main()
