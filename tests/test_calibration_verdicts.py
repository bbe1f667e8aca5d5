"""What calibration says a run shows (twin/hil/calibration.py `verdicts`), on costs whose truth the test knows:
quadratics in log(value / prior) with the minimum, the curvature and the disagreement between groups chosen
here, fitted by the same `quadratic_fit` the search uses."""

import numpy as np
import pytest

from twin.hil.calibration import PRIOR_RANGE, quadratic_fit, verdicts

PARAMS = ("rotor_inertia", "gear_friction")
PRIOR = {"rotor_inertia": 1e-8, "gear_friction": 4e-3}


def samples(group_cost, n_groups=18, n=120, spread=0.25, seed=0):
    """Per-group quadratics fitted about the best of n samples drawn about the prior (log)."""
    rng = np.random.default_rng(seed)
    X = rng.normal(0.0, spread, (n, 2))
    G = np.array([[group_cost(x, g) for g in range(n_groups)] for x in X])
    xb = X[np.argmin(G.sum(axis=1))]
    grads, Hs = quadratic_fit(X - xb, G)
    return grads, Hs, xb


def test_a_parameter_held_at_a_wrong_prior_widens_the_one_it_trades_with():
    # friction 1.46 x its prior, barely shown; the runs see inertia + 0.8 friction (log) sharply: held at its
    # prior, friction drags inertia 35 % off. That inertia must not be called identifiable.
    truth = np.log([1.0, 1.46])

    def cost(x, g):
        d = x - truth
        return 400.0 * (d[0] + 0.8 * d[1]) ** 2 + 0.02 * d[1] ** 2

    grads, Hs, xb = samples(cost)
    _, est = verdicts(grads, Hs, xb, 0.05, PARAMS, PRIOR)
    friction, inertia = est["gear_friction"], est["rotor_inertia"]
    assert friction.value == PRIOR["gear_friction"] and not friction.identifiable
    assert (friction.low, friction.high) == tuple(PRIOR["gear_friction"] * r for r in PRIOR_RANGE["gear_friction"])
    assert inertia.value / PRIOR["rotor_inertia"] > 1.3  # biased, as the runs say with friction held
    assert not inertia.identifiable and inertia.fitted
    assert inertia.low <= PRIOR["rotor_inertia"] <= inertia.high  # the truth stays inside what is left open
    assert inertia.low <= PRIOR["rotor_inertia"] * PRIOR_RANGE["rotor_inertia"][0]  # and its prior range


def test_groups_that_disagree_widen_an_interval_the_noise_alone_would_keep_narrow():
    # each group's own minimum of inertia scattered (log sd 0.6): a model error the hinges show differently,
    # their mean uncertain by about 0.6 / sqrt(18) = 0.14. The residual's noise (s2) alone would pin it (as it
    # does when the groups agree); the jackknife must not.
    scatter = np.random.default_rng(1).normal(0.0, 0.6, 18)
    for offsets, shown in ((np.full(18, 0.1), True), (scatter - scatter.mean() + 0.1, False)):
        def cost(x, g):
            return 50.0 * (x[0] - offsets[g]) ** 2 + 50.0 * x[1] ** 2

        grads, Hs, xb = samples(cost)
        _, est = verdicts(grads, Hs, xb, 1e-6, PARAMS, PRIOR)
        assert est["rotor_inertia"].fitted and est["rotor_inertia"].identifiable == shown, est
        assert est["gear_friction"].identifiable  # the groups agree on friction: it stays pinned


def test_a_sharply_shown_parameter_is_identified_near_its_truth():
    truth = np.log([0.8, 1.2])

    def cost(x, g):
        d = x - truth
        return 300.0 * d[0] ** 2 + 200.0 * d[1] ** 2 + 50.0 * d[0] * d[1]

    grads, Hs, xb = samples(cost)
    _, est = verdicts(grads, Hs, xb, 1e-4, PARAMS, PRIOR)
    for (p, e), t in zip(est.items(), np.exp(truth)):
        assert e.identifiable and e.value / PRIOR[p] == pytest.approx(t, rel=0.01)
        assert e.low < e.value < e.high
