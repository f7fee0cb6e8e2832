"""The joint law of error over model size, data and training length, and the cheapest configuration it names:
planted laws recovered from noisy outcomes, the search and the backtest on a cloud whose law is known."""

from dataclasses import replace

import numpy as np
import pytest

from nsl_hpc.analysis.cheapest import Configurations, backtest, cheaper_share, cheapest_index, cost_interval
from nsl_hpc.analysis.joint_law import JointLaw, JointLawError, bootstrap_joint_laws, fit_joint_law
from nsl_hpc.analysis.nsl_settings import nsl_settings
from nsl_hpc.config import compose_config

SETTINGS = nsl_settings(compose_config(["target=0.1", "sweep_dir=unused"], "predict").nsl).joint
PLANTED = np.log([0.01, 2.0, 0.5, 5.0, 0.4, 1.0, 0.7])  # ln E, (ln A, alpha), (ln B, beta), (ln C, gamma)


def planted_cloud(n: int, seed: int) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """Configurations on a log grid of sizes, their law values and outcomes at or above the law (a run reaches
    at best what its sizes allow: lognormal excess, sigma 0.1)."""
    rng = np.random.default_rng(seed)
    sizes = {"model": np.exp(rng.uniform(np.log(50), np.log(5e3), n)),
             "data": np.exp(rng.uniform(np.log(100), np.log(1e5), n)),
             "length": 2.0 ** rng.integers(1, 12, n)}
    exponents = np.exp(PLANTED[2::2])
    law = JointLaw(("model", "data", "length"), np.concatenate([[PLANTED[0]], np.ravel(np.column_stack(
        [PLANTED[1::2], exponents]))]), 0.0)
    values = np.exp(law.log_predict(sizes))
    return sizes, values, values * np.exp(np.abs(rng.normal(0, 0.1, n)))


def test_a_planted_joint_law_is_recovered_from_outcomes_above_it():
    sizes, values, errors = planted_cloud(300, 0)
    law = fit_joint_law(sizes, errors, SETTINGS)
    assert law.variables == ("model", "data", "length")
    assert np.allclose(law.theta[2::2], [0.5, 0.4, 0.7], rtol=0.1)  # alpha, beta, gamma
    ratio = np.exp(law.log_predict(sizes)) / values
    assert 0.95 < np.median(ratio) < 1.1  # fitted from below: on the law, not on the outcomes' middle
    plain = fit_joint_law(sizes, errors, replace(SETTINGS, above_weight=1.0))
    assert np.median(np.exp(plain.log_predict(sizes)) / values) > np.median(ratio)


def test_a_size_the_grid_does_not_vary_has_no_term_and_too_few_configurations_are_refused():
    sizes, _, errors = planted_cloud(40, 1)
    sizes["length"] = np.full(40, 64.0)
    assert fit_joint_law(sizes, errors, SETTINGS).variables == ("model", "data")
    with pytest.raises(JointLawError, match="min_configurations"):
        fit_joint_law({name: values[:5] for name, values in sizes.items()}, errors[:5], SETTINGS)


def test_the_cheapest_configuration_reaching_a_target_and_its_interval():
    sizes, values, errors = planted_cloud(300, 2)
    seconds = sizes["model"] * sizes["data"] * sizes["length"] * 1e-9  # (n,) a cost growing with every size
    configurations = Configurations([{"index": i} for i in range(300)], sizes, seconds)
    law = fit_joint_law(sizes, errors, SETTINGS)
    target = float(np.quantile(values, 0.1))
    chosen = cheapest_index(law, configurations, target)
    assert chosen is not None and np.exp(law.log_predict(sizes))[chosen] <= target
    truly = np.flatnonzero(values <= target)
    assert seconds[chosen] <= 2 * seconds[truly].min()  # within 2x of the cheapest that truly reaches it
    assert cheapest_index(law, configurations, float(values.min()) / 10) is None
    refits = bootstrap_joint_laws(law, sizes, errors, 30, 0, SETTINGS)
    low, high = cost_interval(refits, configurations, seconds, target, 0.9)
    assert low <= seconds[chosen] <= high < np.inf


def test_the_backtest_fits_the_cheaper_share_and_predicts_the_dearer_best():
    sizes, _, errors = planted_cloud(400, 3)
    seconds = sizes["model"] * sizes["data"] * sizes["length"] * 1e-9
    cheap = cheaper_share(seconds, 0.5)
    assert seconds[cheap].sum() <= 0.5 * seconds.sum() < seconds[cheap].sum() + seconds[~cheap].min()
    tested = backtest(Configurations([{}] * 400, sizes, seconds), errors, 0.5, SETTINGS)
    assert tested.fitted == cheap.sum() and tested.fitted + tested.predicted == 400
    assert 0.7 < tested.best_ratio < 1.4  # the planted law extrapolates: its best of the dearer ones is found
