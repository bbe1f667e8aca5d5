"""What calibration says a run shows (twin/hil/calibration.py `verdicts`), on costs whose truth the test knows:
quadratics in log(value / prior) with the minimum, the curvature and the disagreement between groups chosen
here, fitted by the same `quadratic_fit` the search uses."""

import numpy as np
import pytest

from twin.device.variation import SPREAD
from twin.hil.calibration import bounded_fit, fit_blocks, quadratic_fit, verdicts

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


def test_a_barely_shown_parameter_does_not_make_its_partner_look_identified():
    # friction 1.46 x its prior, barely shown; the runs see inertia + 0.8 friction (log) sharply. Held at its
    # prior, friction would drag inertia 35 % off and make it look pinned there (the rule before): fitted with
    # the prior's pull, friction moves partway and inertia's interval holds what the two trade.
    truth = np.log([1.0, 1.46])

    def cost(x, g):
        d = x - truth
        return 400.0 * (d[0] + 0.8 * d[1]) ** 2 + 0.02 * d[1] ** 2

    grads, Hs, xb = samples(cost)
    _, est = verdicts(grads, Hs, xb, 0.05, PARAMS, PRIOR)
    friction, inertia = est["gear_friction"], est["rotor_inertia"]
    assert not friction.identifiable and 1.0 < friction.value / PRIOR["gear_friction"] < 1.46
    assert friction.low <= PRIOR["gear_friction"] * SPREAD["gear_friction"][0]  # its prior range left open
    assert friction.high >= PRIOR["gear_friction"] * SPREAD["gear_friction"][1]
    assert not inertia.identifiable and inertia.low <= PRIOR["rotor_inertia"] <= inertia.high


def test_groups_that_disagree_widen_an_interval_the_noise_alone_would_keep_narrow():
    # each group's own minimum of inertia scattered (log sd 0.6): a model error the hinges show differently,
    # their mean uncertain by about 0.6 / sqrt(18) = 0.14. The residual's noise (s2) alone would pin it (as it
    # does when the groups agree); the jackknife must not. Scattered by 4, the runs say nothing of it.
    scatter = np.random.default_rng(1).normal(0.0, 1.0, 18)
    scatter = (scatter - scatter.mean()) / scatter.std()
    for offsets, shown in ((np.full(18, 0.1), True), (0.6 * scatter + 0.1, False), (4.0 * scatter + 0.1, None)):
        def cost(x, g):
            return 50.0 * (x[0] - offsets[g]) ** 2 + 50.0 * x[1] ** 2

        grads, Hs, xb = samples(cost)
        _, est = verdicts(grads, Hs, xb, 1e-6, PARAMS, PRIOR)
        if shown is None:  # the hinges disagree far beyond what the prior allows: left at its prior
            assert not est["rotor_inertia"].fitted and "left at its prior" in est["rotor_inertia"].note, est
        else:
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


def _fit_on(group_cost):
    """fit_blocks (search, quadratic, verdicts, acceptance) on a cost of two parameters shared by two hinges of
    one 100-frame run (6 groups), the residual white noise."""
    noise = [np.random.default_rng(0).normal(size=(100, 2))]
    [(x, est, _, _)] = fit_blocks(lambda X: np.array([[group_cost(x[0], g) for g in range(6)] for x in X]),
                                  lambda x: noise, [100], [[0, 1]], PARAMS, [PRIOR], {p: SPREAD[p] for p in PARAMS},
                                  24, 8, 0, 0.15, None)
    return x, est


def test_a_cost_the_quadratic_cannot_follow_keeps_the_best_sample_not_identified():
    # friction's cost two wells (log +-0.3) about a hump at its prior: the quadratic fitted over both puts its
    # mode on the hump, which, replayed, costs far more than the samples in the wells. The best sample is kept,
    # nothing called identifiable, each interval holding its value and the prior range.
    x, est = _fit_on(lambda x, g: 1.0 + 50.0 * (x[0] - 0.1) ** 2 + 40.0 * (x[1] ** 2 - 0.09) ** 2)
    assert abs(abs(x[1]) - 0.3) < 0.1 and abs(x[0] - 0.1) < 0.05
    for p, e in est.items():
        assert not e.identifiable and "best of the search's samples" in e.note
        lo, hi = (PRIOR[p] * r for r in SPREAD[p])
        assert e.low <= min(lo, e.value) and e.high >= max(hi, e.value)
    # a cost the quadratic follows keeps its mode, identified
    x, est = _fit_on(lambda x, g: 1.0 + 50.0 * (x[0] - 0.1) ** 2 + 30.0 * (x[1] - 0.2) ** 2)
    assert np.allclose(x, [0.1, 0.2], atol=0.02) and all(e.identifiable for e in est.values())


def test_bounded_fit_recovers_the_terms_of_parameters_held_while_the_search_ran():
    # a quadratic in five parameters, two of them held at 0 while the free ones' quadratic was fitted: the
    # samples where they vary give their gradient, their Hessian and their products with the free ones exactly
    rng = np.random.default_rng(0)
    free, held = [0, 2, 4], [1, 3]
    H = rng.normal(size=(5, 5))
    H = H @ H.T
    g = rng.normal(size=5)

    def cost(X):
        return (3.0 + X @ g + 0.5 * np.einsum("si,ij,sj->s", X, H, X))[:, None]

    searched = rng.normal(size=(100, 5))
    searched[:, held] = 0.0
    g_free, H_free = quadratic_fit(searched[:, free], cost(searched))
    varied = rng.normal(size=(60, 5))
    grads, Hs = bounded_fit(varied, cost(varied), g_free, H_free, free, held)
    assert np.allclose(grads[0], g) and np.allclose(Hs[0], H)


def test_a_bounded_parameter_widens_what_it_trades_with_and_only_that():
    # the runs show friction + 0.9 cogging (log) sharply, and inertia on its own; the device's cogging is x1.5
    # the twin's nominal. A twin without the cogging as a parameter puts its share into friction and calls that
    # identifiable, 44 % off; bounded (held at its nominal, sampled within its range after the search), friction's
    # interval allows for it anywhere there: it holds the truth and is not called identifiable. Inertia, which
    # trades with nothing, stays identified near its truth either way.
    truth = np.log([0.9, 1.2, 1.5])
    prior = PRIOR | {"cogging": 0.03}
    ranges = {p: SPREAD[p] for p in PARAMS} | {"cogging": (1 / 3, 5 / 3)}
    noise = [np.random.default_rng(0).normal(size=(100, 2))]

    def group_costs(x):  # x (3,): the device's cost, six groups alike
        d = x - truth
        return np.full(6, 1.0 + 300.0 * d[0] ** 2 + 300.0 * (d[1] + 0.9 * d[2]) ** 2)

    for params, bounded in ((PARAMS, ()), (PARAMS + ("cogging",), (2,))):
        [(x, est, _, _)] = fit_blocks(lambda X: np.array([group_costs(np.append(x[0], 0.0)[:3]) for x in X]),
                                      lambda x: noise, [100], [[0, 1]], params, [prior], ranges, 24, 8, 0, 0.15, None, bounded=bounded)
        friction, inertia = est["gear_friction"], est["rotor_inertia"]
        assert inertia.identifiable and inertia.value / PRIOR["rotor_inertia"] == pytest.approx(0.9, rel=0.03)
        true_friction = PRIOR["gear_friction"] * 1.2
        if bounded:
            assert friction.low <= true_friction <= friction.high and not friction.identifiable, friction
            assert est["cogging"].value == prior["cogging"] and "bounded" in est["cogging"].note
            # what the twin, its cogging at the nominal, needs to reproduce the runs stays narrow (what tuning covers)
            low, high = friction.runs_range
            assert low <= friction.value <= high and high / low < 1.35 < friction.high / friction.low, friction
        else:
            assert friction.identifiable and not friction.low <= true_friction <= friction.high, friction
