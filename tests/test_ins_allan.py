"""The white-noise density of a low-pass-filtered IMU stream (:mod:`magnav_ins.ins.allan`): an autopilot's samples
are filtered before they are sent, so ``std x sqrt(dt)`` understates the random walk the filter must assume."""

from __future__ import annotations

import numpy as np
from scipy.signal import butter, lfilter

from magnav_ins.ins.allan import allan_deviation, white_noise_density


def _filtered_noise(density: float, dt: float, n: int, cutoff_hz: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    fs = 1000.0  # the sensor's own rate; sent at 1/dt after a low-pass filter (ArduPilot: 20 Hz, 2nd order)
    white = rng.normal(0.0, density * np.sqrt(fs), (int(n * dt * fs), 2))
    b, a = butter(2, cutoff_hz / (fs / 2))
    return lfilter(b, a, white, axis=0)[:: int(round(dt * fs))][:n]


def test_allan_density_recovers_the_random_walk_that_the_sample_std_understates():
    for seed in (1, 2, 3):  # held-out seeds: the same bound on each
        x = _filtered_noise(6.5e-6, 0.01, 6000, 20.0, seed)
        naive = x.std(axis=0) * np.sqrt(0.01)
        allan = white_noise_density(x, 0.01)
        assert np.all(naive < 0.8 * 6.5e-6)  # the filter hides the noise from the per-sample std
        assert np.all(np.abs(allan / 6.5e-6 - 1.0) < 0.15)


def test_allan_deviation_of_white_noise_falls_as_one_over_sqrt_tau():
    rng = np.random.default_rng(7)
    x = rng.normal(0.0, 1.0, 100_000)
    a1, a10 = allan_deviation(x, 0.01, 0.1), allan_deviation(x, 0.01, 1.0)
    assert abs(float(a1[0]) / float(a10[0]) - np.sqrt(10.0)) < 0.3
    assert np.isnan(allan_deviation(x[:20], 0.01, 0.1)[0])  # fewer than three averages
