"""The cross-entropy method, the one search loop of the tuner (twin.tuning.tuner: log PID gains) and of
calibration (twin.hil.calibration: log plant parameters): an independent Gaussian per dimension, drawn
from, then refitted to the best samples of each generation, smoothed, its spread kept above a floor so
the search never collapses onto one point before its last generation. Both costs are rough (the encoder
quantises the closed loop; the hinges stick and slip), which is why neither uses a gradient.
"""

from __future__ import annotations

import math

import numpy as np

SMOOTHING = 0.3  # the share of the elite's spread in the next generation's (the rest the current one's)


class CrossEntropy:
    """The sampling distribution: mean and spread of each dimension (any shape), samples within low..high."""

    def __init__(self, mean, std, floor: float, low: float = -math.inf, high: float = math.inf):
        self.mean = np.array(mean, float)
        self.std = np.broadcast_to(np.asarray(std, float), self.mean.shape).copy()
        self.floor, self.low, self.high = floor, low, high

    def draw(self, rng: np.random.Generator, population: int, first=None) -> np.ndarray:
        """(population, *shape) samples; sample 0 is `first` where given (the best so far, kept in the race)."""
        x = np.clip(self.mean + self.std * rng.standard_normal((population, *self.mean.shape)), self.low, self.high)
        if first is not None:
            x[0] = first
        return x

    def refit(self, elite: np.ndarray, where=slice(None)) -> None:
        """Move the distribution onto the elite samples ((k, *shape), best first), in the dimensions `where`
        (an index into the first axis of the shape: e.g. one chain's hinges) only."""
        chosen = elite[:, where]
        self.mean[where] = chosen.mean(axis=0)
        self.std[where] = np.maximum((1 - SMOOTHING) * self.std[where] + SMOOTHING * chosen.std(axis=0), self.floor)
