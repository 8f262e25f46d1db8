"""Accuracy guard (issue 19): the embedded demo must not decompose or relight worse than committed.

``R * S = I`` holds by construction and says nothing of accuracy. This test decomposes the embedded
demo (240x180, 6 views, ground truth and relit renders included, so it needs no ../shared data)
with the default configuration, relights it at the demo's relit suns, and fails when a figure is
worse than the committed one by more than its margin.

Figures and margins: ``python benchmarks/bench_guard.py --seeds 8 --out
benchmarks/results/accuracy_guard.json``. A margin is three standard deviations of the figure over
the seeds 0-7 of :class:`mvintrinsic.Config` (the seed draws Step 1's rays and every other random
choice of the method), and at least the largest distance of a seed's figure from the default's:
a change that moves a figure by more is more than another draw of the random samples. When a
change is meant to move a figure, rerun the benchmark and update :data:`COMMITTED` with it (the
second test checks that the two agree).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from bench_guard import measure

from mvintrinsic.cli import demo_scene_path

#: figure -> (committed value, margin, larger is better); benchmarks/results/accuracy_guard.json.
COMMITTED = {
    "lmse_reflectance": (0.03380, 0.00146, False),
    "lmse_shading": (0.13686, 0.00856, False),
    "ber": (0.15982, 0.00433, False),
    "relit_psnr_az+15": (26.50417, 0.09577, True),
    "relit_psnr_el+10": (24.88715, 0.10781, True),
}
REPORT = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "accuracy_guard.json"


def worse(figures: dict[str, float]) -> dict[str, str]:
    """The figures worse than committed by more than their margin, with a readable reason."""
    out = {}
    for key, (value, margin, larger_is_better) in COMMITTED.items():
        got = figures[key]
        bad = got < value - margin if larger_is_better else got > value + margin
        if bad:
            out[key] = f"{got:.5f} against {value:.5f} +- {margin:.5f} ({'higher' if larger_is_better else 'lower'} is better)"
    return out


def test_demo_is_no_less_accurate_than_committed():
    figures = measure(demo_scene_path(), seed=0)
    assert set(figures) == set(COMMITTED)
    assert not worse(figures), f"accuracy regression on the embedded demo: {worse(figures)}"


def test_guard_detects_a_regression_of_one_margin():
    """The comparison itself: a figure just past its margin (on the bad side) is reported, one within is not."""
    within = {k: v + (-0.5 if better else 0.5) * m for k, (v, m, better) in COMMITTED.items()}
    assert worse(within) == {}
    for key, (value, margin, better) in COMMITTED.items():
        past = dict(within, **{key: value + (-1.01 if better else 1.01) * margin})
        assert list(worse(past)) == [key]


def test_committed_figures_match_the_benchmark_report():
    report = json.loads(REPORT.read_text())
    for key, (value, margin, larger_is_better) in COMMITTED.items():
        assert report["figures"][key] == pytest.approx(value, abs=1e-5), key
        assert report["margins"][key] == pytest.approx(margin, abs=1e-5), key
        assert report["larger_is_better"][key] is larger_is_better, key
