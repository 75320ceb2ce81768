"""Mutual-information estimators: API contract, correctness on known distributions, gradients."""

import json
import math

import pytest
import torch

from lerobot_maxmi.mi import ESTIMATORS, InfoNet, load_estimator, state_mi
from lerobot_maxmi.mi.estimators import InfoNetEstimator
from lerobot_maxmi.mi.evaluate import evaluate_estimators, format_table
from lerobot_maxmi.mi.ground_truth import (
    bivariate_gaussian_mi,
    random_gaussian_mixtures,
    sample_bivariate_gaussian,
)
from lerobot_maxmi.mi.infonet import InfoNetConfig
from lerobot_maxmi.mi.normalize import (
    binned_copula_mi,
    hard_rank,
    knn_copula_mi,
    kth_neighbor_squared_distances,
    rank_normalize,
)

DIFFERENTIABLE = ["infonet", "infonet_regression", "gaussian"]


def correlated_sets(rhos, n, generator):
    points = sample_bivariate_gaussian(torch.tensor(rhos, dtype=torch.float64), n, generator).float()
    return points[..., 0], points[..., 1]


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_shape_and_determinism(name, generator):
    x, y = correlated_sets([0.0, 0.5, 0.9], 100, generator)
    estimator = load_estimator(name)
    first, second = estimator(x, y), estimator(x, y)
    assert first.shape == (3,)
    assert torch.isfinite(first).all()
    torch.testing.assert_close(first, second)


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_orders_correlated_gaussians(name, generator):
    rhos = [0.0, 0.4, 0.7, 0.9, 0.97]
    x, y = correlated_sets(rhos, 1000, generator)
    estimate = load_estimator(name)(x, y)
    assert (estimate.diff() > 0).all(), f"{name} estimates {estimate.tolist()} are not increasing in rho"


@pytest.mark.parametrize("name", ["infonet", "infonet_regression", "gaussian", "ksg"])
def test_close_to_closed_form_on_gaussians(name, generator):
    rhos = torch.linspace(-0.9, 0.9, 16)
    x, y = correlated_sets(rhos.tolist(), 1000, generator)
    error = (load_estimator(name)(x, y) - bivariate_gaussian_mi(rhos)).abs().mean()
    assert error < 0.08, f"{name}: mean abs error {error:.3f} nats"


@pytest.mark.parametrize("name", DIFFERENTIABLE)
def test_gradients_reach_the_samples(name, generator):
    x, y = correlated_sets([0.3, 0.8], 100, generator)
    x.requires_grad_(True)
    load_estimator(name)(x, y).sum().backward()
    assert torch.isfinite(x.grad).all()
    assert x.grad.abs().sum() > 0


@pytest.mark.parametrize("name", DIFFERENTIABLE)
@pytest.mark.parametrize("scale", [0.0, 1e-36])
def test_state_mi_gradients_stay_finite_on_constant_dimensions(name, scale, generator):
    """A concept parked on frame 0 reads a state dimension as (soft-argmax ~1e-36) × (next frame): constant
    up to rounding. Per-dim MI counts it as 0, and its gradient must not turn the whole batch to NaN."""
    s_a = torch.randn(2, 64, 3, generator=generator)
    s_a[..., 0] = scale * torch.randn(2, 64, generator=generator)
    s_b = (s_a + 0.1 * torch.randn(2, 64, 3, generator=generator)).requires_grad_(True)
    s_a.requires_grad_(True)
    state_mi(s_a, s_b, load_estimator(name), mode="per_dim").sum().backward()
    assert torch.isfinite(s_a.grad).all() and torch.isfinite(s_b.grad).all()
    assert s_a.grad[..., 1:].abs().sum() > 0


def test_gradient_ascent_increases_dependence(generator):
    """Following d(MI)/dx should make x more dependent on y: the signal MaxMI trains on."""
    x, y = correlated_sets([0.2], 200, generator)
    x = x.clone().requires_grad_(True)
    estimator = load_estimator("infonet")
    before = estimator(x, y).item()
    optimizer = torch.optim.Adam([x], lr=0.05)  # per-sample gradients scale as 1/N; Adam rescales them
    for _ in range(40):
        optimizer.zero_grad()
        (-estimator(x, y)).sum().backward()
        optimizer.step()
    assert estimator(x, y).item() > before + 0.1


@pytest.mark.parametrize(
    ("x", "y", "message"),
    [
        (torch.zeros(2, 10), torch.zeros(2, 11), "same shape"),
        (torch.zeros(10), torch.zeros(10), "2-D"),
        (torch.zeros(2, 3), torch.zeros(2, 3), "at least 4"),
        (torch.full((1, 10), float("nan")), torch.zeros(1, 10), "NaN"),
        (torch.zeros(1, 10, dtype=torch.long), torch.zeros(1, 10, dtype=torch.long), "floating point"),
    ],
)
def test_bad_input_is_rejected_clearly(x, y, message):
    with pytest.raises((ValueError, TypeError), match=message):
        load_estimator("gaussian")(x, y)


def test_unknown_estimator_lists_valid_names():
    with pytest.raises(ValueError, match="infonet, infonet_regression, ksg, gaussian"):
        load_estimator("mine")


def test_rank_normalize_handles_ties_and_passes_gradients():
    x = torch.tensor([[3.0, 1.0, 2.0, 2.0], [5.0, 5.0, 5.0, 5.0]], requires_grad=True)
    ranks = rank_normalize(x)
    torch.testing.assert_close(ranks.detach(), torch.tensor([[0.875, 0.125, 0.5, 0.5], [0.5, 0.5, 0.5, 0.5]]))
    ranks[0, 0].backward()
    assert x.grad[0, 0] > 0 and torch.isfinite(x.grad).all()


def test_binned_copula_mi_is_zero_when_independent_and_log_bins_when_identical(generator):
    u, v = (hard_rank(torch.randn(4, 4096, generator=generator)) for _ in range(2))
    assert binned_copula_mi(u, v, bins=8).abs().max() < 0.01
    n, bins = 120, 6
    same = hard_rank(torch.randn(1, n, generator=generator))
    expected = math.log(bins) + (bins - 1) / (2 * n)  # plug-in MI plus the Miller–Madow term
    torch.testing.assert_close(binned_copula_mi(same, same, bins), torch.tensor([expected]))


def test_knn_copula_mi_orders_dependence_and_stays_finite_on_ties(generator):
    a = torch.randn(3, 1000, generator=generator)
    rho = torch.tensor([[0.0], [0.5], [0.9]])
    b = rho * a + (1 - rho.square()).sqrt() * torch.randn(3, 1000, generator=generator)
    mi = knn_copula_mi(hard_rank(a), hard_rank(b), neighbors=(3, 10))
    truth = bivariate_gaussian_mi(rho)
    assert (mi - truth).abs().max() < 0.1 and (mi[1:] > mi[:-1] + 0.05).all()
    x = torch.tensor([[1.0, 1.0, 2.0, 2.0, 3.0, 3.0]], requires_grad=True)  # ties, fewer points than k
    tied = knn_copula_mi(rank_normalize(x), rank_normalize(x), neighbors=(1, 10))
    tied.sum().backward()
    assert torch.isfinite(tied).all() and torch.isfinite(x.grad).all()


def test_windowed_neighbour_search_matches_all_pairs(generator):
    """Large sets search a window around each point and fall back to the whole set in sparse regions."""
    dense = 0.1 * torch.rand(2, 560, 2, generator=generator)
    sparse = torch.rand(2, 40, 2, generator=generator)  # far from the dense points: the fallback's case
    points = torch.cat([dense, sparse], dim=1)
    points[:, :20] = points[:, 20:40]  # coincident points
    neighbors = (1, 3, 10)
    found = kth_neighbor_squared_distances(points, neighbors)
    distances = torch.cdist(points, points, compute_mode="donot_use_mm_for_euclid_dist")
    distances = distances + torch.diag_embed(torch.full_like(points[..., 0], float("inf")))
    expected = distances.sort(dim=-1).values[..., [k - 1 for k in neighbors]].square()
    # found comes back sorted by the first coordinate: compare each k's values as sets.
    torch.testing.assert_close(found.sort(dim=1).values, expected.sort(dim=1).values, atol=1e-6, rtol=0)


def test_monte_carlo_mi_matches_closed_form_for_one_component(generator):
    mixtures = random_gaussian_mixtures(8, max_components=1, generator=generator)
    cov = mixtures.covariances[:, 0]
    rho = cov[:, 0, 1] / (cov[:, 0, 0] * cov[:, 1, 1]).sqrt()
    torch.testing.assert_close(
        mixtures.monte_carlo_mi(20_000, generator), bivariate_gaussian_mi(rho), atol=0.02, rtol=0
    )


def test_state_mi_per_dim_ignores_constant_dimensions(generator):
    s_a = torch.randn(2, 50, 4, generator=generator)
    s_b = s_a + 0.1 * torch.randn(2, 50, 4, generator=generator)
    s_a[..., 3] = 1.0  # constant in s_a: contributes 0, never NaN
    estimator = load_estimator("gaussian")
    mi = state_mi(s_a, s_b, estimator, mode="per_dim")
    assert mi.shape == (2,) and torch.isfinite(mi).all()
    three_dims = state_mi(s_a[..., :3], s_b[..., :3], estimator, mode="per_dim")
    torch.testing.assert_close(mi, three_dims * 3 / 4)


def test_state_mi_sliced_is_seeded_and_orders_dependence(generator):
    s_a = torch.randn(1, 200, 5, generator=generator)
    dependent = torch.cat([s_a + 0.1 * torch.randn(1, 200, 5, generator=generator), torch.randn(1, 200, 5)])
    estimator = load_estimator("gaussian")
    mi = state_mi(s_a.expand(2, -1, -1), dependent, estimator, "sliced", 32, torch.Generator().manual_seed(1))
    again = state_mi(
        s_a.expand(2, -1, -1), dependent, estimator, "sliced", 32, torch.Generator().manual_seed(1)
    )
    torch.testing.assert_close(mi, again)
    assert mi[0] > mi[1] + 0.05


def test_state_mi_rejects_unknown_mode():
    with pytest.raises(ValueError, match="per_dim, sliced"):
        state_mi(torch.zeros(1, 8, 2), torch.zeros(1, 8, 2), load_estimator("gaussian"), mode="pca")


def test_infonet_save_and_load_round_trip(tmp_path, generator):
    model = InfoNet(**vars(InfoNetConfig(dim=16, num_latents=4, num_layers=1, grid_size=8)))
    model.save_pretrained(tmp_path / "infonet")
    x, y = correlated_sets([0.5], 64, generator)
    for name, head in (("infonet", "critic"), ("infonet_regression", "regression")):
        reloaded = load_estimator(name, pretrained=str(tmp_path / "infonet"))
        torch.testing.assert_close(reloaded(x, y), InfoNetEstimator(model, head)(x, y))
    assert (tmp_path / "infonet" / "model.safetensors").exists()


def test_infonet_saved_before_the_binned_and_knn_statistics_still_loads(tmp_path, generator):
    """Weights saved before `histogram_bins` and `knn_neighbors` existed: a head reading three statistics."""
    sizes = {
        **vars(InfoNetConfig(dim=16, num_latents=4, num_layers=1, grid_size=8)),
        "histogram_bins": (),
        "knn_neighbors": (),
    }
    InfoNet(**sizes).save_pretrained(tmp_path / "old")
    config = json.loads((tmp_path / "old" / "config.json").read_text())
    del config["histogram_bins"], config["knn_neighbors"]
    (tmp_path / "old" / "config.json").write_text(json.dumps(config))
    x, y = correlated_sets([0.5], 64, generator)
    assert torch.isfinite(load_estimator("infonet_regression", pretrained=str(tmp_path / "old"))(x, y)).all()


def test_hub_repo_id_goes_through_the_hub_client():
    """A repo id is resolved by huggingface_hub (offline here, so it stops at the network boundary)."""
    from huggingface_hub.errors import HfHubHTTPError, LocalEntryNotFoundError, OfflineModeIsEnabled

    with pytest.raises((OfflineModeIsEnabled, LocalEntryNotFoundError, HfHubHTTPError)):
        load_estimator("infonet", pretrained="lerobot-maxmi-tests/no-such-infonet")


def test_attention_rewrites_match_torch_modules(generator):
    """InfoNet runs its attention layers through `attend` / `pre_norm_layer` for speed; same results."""
    from lerobot_maxmi.mi.infonet import attend, pre_norm_layer

    attention = torch.nn.MultiheadAttention(16, 4, batch_first=True)
    queries, context = torch.randn(5, 16, generator=generator), torch.randn(3, 7, 16, generator=generator)
    batched = queries.expand(3, -1, -1)
    expected = attention(batched, context, context, need_weights=False)[0]
    torch.testing.assert_close(attend(attention, batched, context), expected)
    torch.testing.assert_close(attend(attention, queries, context), expected)
    layer = torch.nn.TransformerEncoderLayer(
        16, 4, 64, dropout=0.0, activation="gelu", batch_first=True, norm_first=True
    )
    torch.testing.assert_close(pre_norm_layer(layer, context), layer(context))


def test_accuracy_rows_score_each_estimator_with_its_standard_error():
    rows = evaluate_estimators(
        ["gaussian", "ksg"], ["gaussian", "gmm"], [64], count=16, seed=0, mc_samples=2000
    )

    assert [(r.family, r.estimator) for r in rows] == [
        ("gaussian", "gaussian"),
        ("gaussian", "ksg"),
        ("gmm", "gaussian"),
        ("gmm", "ksg"),
    ]
    assert rows[0].mae < rows[2].mae  # the copula's model is right for Gaussians, wrong for mixtures
    assert all(0 < r.mae_standard_error < r.mae for r in rows)
    first = rows[0]
    assert f"| gaussian | 64 | gaussian | {first.mae:.4f} ± {first.mae_standard_error:.4f} |" in format_table(
        rows
    )


def test_accuracy_rows_score_other_infonet_weights_when_given(tmp_path):
    torch.manual_seed(0)
    InfoNet(**vars(InfoNetConfig(dim=16, num_latents=4, num_layers=1, grid_size=8))).save_pretrained(tmp_path)

    def maes(weights):
        rows = evaluate_estimators(
            ["infonet", "gaussian"], ["gaussian"], [64], count=8, seed=0, infonet_weights=weights
        )
        return [r.mae for r in rows]

    (shipped_infonet, shipped_copula), (other_infonet, other_copula) = maes(None), maes(str(tmp_path))
    assert other_infonet != shipped_infonet
    assert other_copula == shipped_copula  # the other estimators keep their own settings
