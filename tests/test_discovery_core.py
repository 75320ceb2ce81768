"""KSL-Net, the MaxMI losses and NMS: the paper's equations, checked one by one."""

import torch

from lerobot_maxmi.discovery.ksl_net import KSLNet, MaxOverTimeLinear, resample, soft_argmax, to_episode_frame
from lerobot_maxmi.discovery.losses import (
    diversity_loss,
    interpolate_states,
    maxmi_loss,
    ordering_loss,
    released_maxmi_loss,
    released_shifted_states,
)
from lerobot_maxmi.discovery.nms import kept_indices, shared_concepts
from lerobot_maxmi.discovery.processor import MaxmiDiscoveryStep, load_localizer, save_localizer
from lerobot_maxmi.mi import load_estimator


def linear_trajectories(batch=3, length=20, dims=2):
    return torch.arange(length, dtype=torch.float32)[None, :, None].expand(batch, -1, dims).clone()


def test_ksl_net_shapes_and_round_trip(tmp_path):
    net = KSLNet(state_dim=5, length=16, num_concepts=3, embed_dim=4, encoder_dims=(32, 32), head_dims=(16,))
    states = torch.randn(4, 16, 5)
    logits = net(states)
    assert logits.shape == (4, 3, 16)
    net.save_pretrained(tmp_path)
    torch.testing.assert_close(KSLNet.from_pretrained(tmp_path)(states), logits)


def test_spread_concepts_start_in_order_and_survive_a_save(tmp_path):
    torch.manual_seed(0)
    sizes = dict(state_dim=2, length=50, num_concepts=4, embed_dim=4, encoder_dims=(16,), head_dims=(16,))
    states = torch.randn(3, 50, 2)
    paper = soft_argmax(KSLNet(**sizes)(states))
    assert (paper - 24.5).abs().max() < 2  # the untrained head: every concept near the middle
    spread = KSLNet(**sizes, concept_start="spread")
    assert (soft_argmax(spread(states)).diff(dim=1) > 5).all()  # one concept per stretch, in order
    architecture = {k: sizes[k] for k in ("embed_dim", "encoder_dims", "head_dims")}
    step = MaxmiDiscoveryStep.from_net(spread, [0, 1, 2, 3], True, concept_start="spread", **architecture)
    save_localizer(step, tmp_path)
    episodes = list(torch.randn(2, 60, 2))
    assert load_localizer(tmp_path).key_frames(episodes) == step.key_frames(episodes)


def test_ksl_net_uses_position_and_concept():
    torch.manual_seed(0)
    net = KSLNet(state_dim=2, length=8, num_concepts=2, embed_dim=4, encoder_dims=(16,), head_dims=(16,))
    logits = net(torch.zeros(1, 8, 2))  # identical states: only the embeddings can differ
    assert not torch.allclose(logits[0, 0], logits[0, 1])


def test_max_over_time_linear_matches_the_dense_gradient():
    torch.manual_seed(0)
    x = torch.randn(3, 2, 7, 5, dtype=torch.float64, requires_grad=True)
    weight = torch.randn(4, 5, dtype=torch.float64, requires_grad=True)
    bias = torch.randn(4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(MaxOverTimeLinear.apply, (x, weight, bias))
    dense = torch.nn.functional.linear(x, weight, bias).max(dim=2).values
    grad = torch.randn_like(dense)
    expected = torch.autograd.grad(dense, (x, weight, bias), grad)
    actual = torch.autograd.grad(MaxOverTimeLinear.apply(x, weight, bias), (x, weight, bias), grad)
    for a, e in zip(actual, expected, strict=True):
        torch.testing.assert_close(a, e)


def test_soft_argmax_of_a_sharp_peak_is_its_index():
    logits = torch.full((1, 2, 10), -1e4)
    logits[0, 0, 3], logits[0, 1, 7] = 0.0, 0.0
    torch.testing.assert_close(soft_argmax(logits), torch.tensor([[3.0, 7.0]]))


def test_interpolation_is_linear_and_differentiable_in_time():
    states = torch.randn(2, 10, 3)
    t = torch.tensor([[2.0, 4.25], [0.0, 9.0]], requires_grad=True)
    gathered = interpolate_states(states, t)
    torch.testing.assert_close(gathered[0, 0], states[0, 2])
    torch.testing.assert_close(gathered[0, 1], 0.75 * states[0, 4] + 0.25 * states[0, 5])
    torch.testing.assert_close(gathered[1, 1], states[1, 9])
    gathered[0, 1].sum().backward()
    torch.testing.assert_close(t.grad[0, 1], (states[0, 5] - states[0, 4]).sum())


def test_released_gather_extrapolates_to_t_not_t_minus_two():
    """Documents the released code's quirk: on a straight line it returns s(t), not s(t − 2)."""
    states = linear_trajectories()
    t = torch.tensor([[5.5], [8.25], [12.0]])
    torch.testing.assert_close(released_shifted_states(states, t)[..., 0], t)
    torch.testing.assert_close(interpolate_states(states, t - 2)[..., 0], t - 2)


def test_maxmi_loss_gives_one_mi_per_concept_and_a_gradient():
    torch.manual_seed(0)
    states = torch.cumsum(torch.randn(32, 30, 4), dim=1)
    t_hat = torch.tensor([5.0, 15.0, 25.0]).expand(32, -1).clone().requires_grad_(True)
    estimator = load_estimator("gaussian")
    loss, per_concept = maxmi_loss(states, t_hat, delta_t=2.0, estimator=estimator)
    assert per_concept.shape == (3,)
    torch.testing.assert_close(loss, -per_concept.sum())
    loss.backward()
    assert torch.isfinite(t_hat.grad).all() and t_hat.grad.abs().sum() > 0
    assert released_maxmi_loss(states, t_hat.detach(), estimator).ndim == 0


def test_diversity_loss_prefers_spread_concepts():
    together = torch.tensor([[10.0, 10.5, 11.0]])
    spread = torch.tensor([[2.0, 10.0, 18.0]])
    assert diversity_loss(spread) < diversity_loss(together)
    assert diversity_loss(spread) < 0.01


def test_ordering_loss_penalizes_reversed_concepts():
    assert ordering_loss(torch.tensor([[2.0, 10.0, 18.0]])) < ordering_loss(torch.tensor([[18.0, 10.0, 2.0]]))


def test_resampled_indices_map_back_to_episode_frames():
    episode = torch.arange(41, dtype=torch.float32).unsqueeze(-1)  # state = frame index
    resampled = resample(episode, 11)
    torch.testing.assert_close(resampled[:, 0], torch.arange(0, 41, 4, dtype=torch.float32))
    assert to_episode_frame(torch.tensor([0.0, 2.5, 10.0]), 41, 11).tolist() == [0, 10, 40]


def test_nms_keeps_the_most_confident_of_close_concepts():
    positions, scores = [10, 12, 30, 31, 50], [0.2, 0.9, 0.5, 0.4, 0.1]
    assert kept_indices(positions, scores, radius=3) == [1, 2, 4]  # sorted by position
    # With the final frame appended (at 1.0), a concept within the radius of it is dropped too.
    assert shared_concepts([0.10, 0.12, 0.97], [0.2, 0.9, 0.8], 0.05, append_final=True) == [1]
    assert shared_concepts([0.40], [1.0], 0.05, append_final=False) == [0]
