"""The Fig. 2 benchmark's MI curve: it must peak where consecutive states depend on each other."""

import math

import torch

from lerobot_maxmi.discovery.annotate import DatasetLocation
from lerobot_maxmi.mi import load_estimator
from tests.conftest import load_benchmark

mi_peak = load_benchmark("mi_peak")


def test_mi_curve_peaks_at_the_planted_dependence():
    # Independent noise frames, except that at each episode's anchor the state repeats the one Δt
    # earlier (plus a little noise): MI is high at σ = 0 and near zero at every other shift.
    generator = torch.Generator().manual_seed(0)
    cfg = mi_peak.MIPeakConfig(dataset=DatasetLocation(repo_id="local/synthetic"), delta_t=2, min_episodes=8)
    episodes, anchors = [], []
    for index in range(64):
        states = torch.randn(40, 3, generator=generator)
        anchor = 15 + index % 10
        states[anchor] = states[anchor - 2] + 0.05 * torch.randn(3, generator=generator)
        episodes.append(states)
        anchors.append(anchor)
    shifts = list(range(-4, 5))
    curve = mi_peak.mi_curve(episodes, anchors, shifts, cfg, load_estimator("ksg"))
    assert mi_peak.peak(shifts, curve) == (curve[4], 0)
    assert curve[4] > 1.0 and max(curve[:4] + curve[5:]) < 0.3


def test_mi_curve_is_nan_where_too_few_episodes_reach():
    cfg = mi_peak.MIPeakConfig(dataset=DatasetLocation(repo_id="local/synthetic"), min_episodes=8)
    episodes = [torch.randn(10, 2) for _ in range(8)]
    curve = mi_peak.mi_curve(episodes, [9] * 8, [0, 1], cfg, load_estimator("ksg"))
    assert not math.isnan(curve[0]) and math.isnan(curve[1])


def test_sliced_curve_scores_every_shift_with_the_same_projections():
    # Episodes that repeat with period 8 give identical pair sets at σ = 0 and σ = 8, so the two
    # shifts must get identical MI; fresh projections per shift would give different values.
    generator = torch.Generator().manual_seed(0)
    cfg = mi_peak.MIPeakConfig(dataset=DatasetLocation(repo_id="local/synthetic"), state_mi_mode="sliced")
    episodes = [torch.randn(8, 5, generator=generator).repeat(4, 1) for _ in range(32)]
    curve = mi_peak.mi_curve(episodes, [12] * 32, [0, 8], cfg, load_estimator("ksg"))
    assert curve[0] == curve[1]
