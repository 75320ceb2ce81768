"""Mutual-information estimators behind one call signature: ``est(x, y) -> Tensor[B]``.

``x`` and ``y`` are raw float tensors of shape (B, N): B independent sets of N paired scalar
samples. Each estimator returns MI in nats per set.
"""

from collections.abc import Callable
from importlib.resources import files

import numpy as np
import torch
from sklearn.feature_selection import mutual_info_regression
from torch import Tensor

from lerobot_maxmi.mi.infonet import HEADS, InfoNet
from lerobot_maxmi.mi.normalize import check_pairs, gaussian_copula_mi, rank_normalize

SHIPPED_INFONET = files("lerobot_maxmi.mi") / "weights" / "infonet"


class MIEstimator:
    """Validates the input, then estimates; subclasses implement `estimate`."""

    differentiable: bool = True

    def __call__(self, x: Tensor, y: Tensor) -> Tensor:
        check_pairs(x, y)
        return self.estimate(x, y)

    def estimate(self, x: Tensor, y: Tensor) -> Tensor:
        raise NotImplementedError


class KSGEstimator(MIEstimator):
    """Kraskov–Stögbauer–Grassberger k-NN estimator (scikit-learn); a reference, not differentiable."""

    differentiable = False

    def __init__(self, k: int = 3, seed: int = 0):
        self.k = k
        self.seed = seed

    def estimate(self, x: Tensor, y: Tensor) -> Tensor:
        xs, ys = x.detach().cpu().double().numpy(), y.detach().cpu().double().numpy()
        values = [
            mutual_info_regression(a[:, None], b, n_neighbors=self.k, random_state=self.seed)[0]
            for a, b in zip(xs, ys, strict=True)
        ]
        return torch.as_tensor(np.asarray(values), dtype=x.dtype, device=x.device)


class GaussianCopulaEstimator(MIEstimator):
    """MI of the Gaussian copula: normal scores of the ranks, then −½ log(1 − ρ²)."""

    def estimate(self, x: Tensor, y: Tensor) -> Tensor:
        return gaussian_copula_mi(rank_normalize(x), rank_normalize(y))


class InfoNetEstimator(MIEstimator):
    """Frozen InfoNet read through one of its heads (``critic``: DV bound, ``regression``: direct)."""

    def __init__(self, model: InfoNet, head: str = "critic"):
        if head not in HEADS:
            raise ValueError(f"unknown InfoNet head {head!r}; choose one of {', '.join(HEADS)}")
        self.model = model.eval().requires_grad_(False)
        self.head = head

    def estimate(self, x: Tensor, y: Tensor) -> Tensor:
        device = next(self.model.parameters()).device
        u, v = (rank_normalize(t.to(device=device, dtype=torch.float32)) for t in (x, y))
        return self.model(u, v, head=self.head).to(device=x.device, dtype=x.dtype)


def load_infonet(pretrained: str | None = None, device: str | torch.device | None = None) -> InfoNet:
    """InfoNet weights from a local directory or hub repo id; the shipped weights by default."""
    source = str(pretrained) if pretrained else str(SHIPPED_INFONET)
    return InfoNet.from_pretrained(source).to(resolve_device(device))


def resolve_device(device: str | torch.device | None) -> torch.device:
    if device is None or device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


ESTIMATORS: dict[str, Callable[..., MIEstimator]] = {
    "infonet": lambda device=None, pretrained=None: InfoNetEstimator(
        load_infonet(pretrained, device), "critic"
    ),
    "infonet_regression": lambda device=None, pretrained=None: InfoNetEstimator(
        load_infonet(pretrained, device), "regression"
    ),
    "ksg": lambda device=None: KSGEstimator(),
    "gaussian": lambda device=None: GaussianCopulaEstimator(),
}


def load_estimator(name: str = "infonet", device: str | torch.device | None = None, **options) -> MIEstimator:
    """Build the estimator registered as `name` (see `ESTIMATORS`)."""
    if name not in ESTIMATORS:
        raise ValueError(f"unknown MI estimator {name!r}; valid names: {', '.join(ESTIMATORS)}")
    return ESTIMATORS[name](device=device, **options)
