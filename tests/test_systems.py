"""The simulated benchmark systems obey their port-Hamiltonian structure and stay bounded."""

import dataclasses

import numpy as np
import pytest
from scipy.integrate import odeint

from nsl_hpc.studies.input_state.data import simulate_experiments
from nsl_hpc.systems import build_system
from nsl_hpc.systems.simulation import Multisine, draw_multisine, simulate
from tests.helpers import SYSTEM_NAMES, power_balance, system_settings

# Largest |state| seen over 5 study trajectories: spring 3.2, ball 3.2, motor 3.7; bounds with margin.
STATE_BOUND = {"spring": 8.0, "ball": 10.0, "motor": 10.0}
# Each system, and the spring with the constants of the authors' code (inputs on the positions).
VARIANTS = [(name, ()) for name in SYSTEM_NAMES] + [("spring", ("system.constants=authors",))]
VARIANT_IDS = [*SYSTEM_NAMES, "spring-authors"]


@pytest.mark.parametrize(("name", "overrides"), VARIANTS, ids=VARIANT_IDS)
def test_structure_matrices(name, overrides):
    cfg = system_settings(name, *overrides)
    system = build_system(cfg)
    x = np.random.default_rng(0).normal(size=(50, system.state_dim))
    J, R = system.interconnection(x), system.dissipation(x)
    np.testing.assert_allclose(J, -np.swapaxes(J, 1, 2), atol=0)
    np.testing.assert_allclose(R, np.swapaxes(R, 1, 2), atol=0)
    assert np.linalg.eigvalsh(R).min() >= -1e-12
    assert system.hamiltonian(x).min() >= 0


@pytest.mark.parametrize(("name", "overrides"), VARIANTS, ids=VARIANT_IDS)
def test_power_balance_along_trajectories(name, overrides):
    """dH/dt = -grad H^T R grad H + y^T u pointwise, and integrated along a simulated trajectory."""
    cfg = system_settings(name, *overrides)
    system = build_system(cfg)
    (trajectory,) = simulate_experiments(cfg, seed=7, count=1)
    pointwise = np.sum(system.grad_hamiltonian(trajectory.x) * trajectory.dx, axis=1)
    balance = power_balance(system, trajectory.x, trajectory.u)
    np.testing.assert_allclose(pointwise, balance, rtol=1e-10, atol=1e-10 * np.abs(balance).max())

    # Integrate the supplied-minus-dissipated power next to the state; it must equal H(x(t)) - H(x(0)).
    rng = np.random.default_rng(3)
    box = np.asarray(cfg.initial_box)
    x0 = rng.uniform(box[:, 0], box[:, 1])
    excitation = draw_multisine(rng, 1, system.input_dim, **dataclasses.asdict(cfg.input))
    n = system.state_dim

    def augmented(state, t):
        x, u = state[None, :n], excitation(t)[0]
        return np.append(system.derivative(x, u)[0], power_balance(system, x, u)[0])

    t = np.linspace(0.0, 2.0, 201)
    solution = odeint(augmented, np.append(x0, 0.0), t, rtol=1e-11, atol=1e-11)
    energy_change = system.hamiltonian(solution[:, :n]) - system.hamiltonian(x0[None])
    scale = np.abs(energy_change).max() + system.hamiltonian(x0[None])[0]
    np.testing.assert_allclose(energy_change, solution[:, n], atol=1e-7 * scale)


@pytest.mark.parametrize(("name", "overrides"), VARIANTS, ids=VARIANT_IDS)
def test_trajectories_finite_and_bounded(name, overrides):
    cfg = system_settings(name, *overrides)
    for trajectory in simulate_experiments(cfg, seed=0, count=5):
        assert trajectory.x.shape == (1000, len(cfg.initial_box))
        assert np.all(np.isfinite(trajectory.x)) and np.all(np.isfinite(trajectory.dx))
        assert np.abs(trajectory.x).max() < STATE_BOUND[name]
        np.testing.assert_allclose(trajectory.t[1] - trajectory.t[0], 0.01)


def test_the_springs_inputs_drive_the_momenta_in_the_paper_and_the_positions_in_the_authors_code():
    x = np.zeros((1, 4))
    paper = build_system(system_settings("spring")).input_matrix(x)[0]
    authors = build_system(system_settings("spring", "system.constants=authors")).input_matrix(x)[0]
    np.testing.assert_array_equal(paper, [[0, 0], [1, 0], [0, 0], [0, 1]])  # x = (q1, p1, q2, p2)
    np.testing.assert_array_equal(authors, [[1, 0], [0, 0], [0, 1], [0, 0]])


def test_multisine_has_the_configured_harmonics():
    rng = np.random.default_rng(0)
    excitation = draw_multisine(rng, experiments=1, channels=2, amplitude=0.4, f0_hz=0.1, harmonics=40)
    t = np.arange(1000) * 0.01  # exactly one period of f0
    u = excitation(t)[:, 0]
    spectrum = np.abs(np.fft.rfft(u, axis=0)) / (len(t) / 2)
    np.testing.assert_allclose(spectrum[1:41], 0.4, rtol=1e-9)
    assert spectrum[41:].max() < 1e-9
    assert not np.allclose(u[:, 0], u[:, 1])  # independent phases per channel
    authors = draw_multisine(np.random.default_rng(0), 1, 2, amplitude=0.4, f0_hz=0.1, harmonics=40,
                             first_harmonic=0)(t)[:, 0]  # k = 0..39: a constant a sin(phi_0) and 39 sines
    spectrum = np.abs(np.fft.rfft(authors, axis=0)) / (len(t) / 2)
    np.testing.assert_allclose(spectrum[1:40], 0.4, rtol=1e-9)
    assert spectrum[40:].max() < 1e-9
    np.testing.assert_allclose(authors.mean(axis=0), 0.4 * np.sin(excitation.phases[0, :, 0]), rtol=1e-9)


@pytest.mark.parametrize("name", SYSTEM_NAMES)
def test_experiments_simulated_together_match_each_simulated_alone(name):
    """The test set's 100 experiments are one odeint call; each agrees with its own integration."""
    cfg = system_settings(name)
    system = build_system(cfg)
    rng = np.random.default_rng(11)
    box = np.asarray(cfg.initial_box)
    x0 = rng.uniform(box[:, 0], box[:, 1], size=(6, len(box)))
    excitation = draw_multisine(rng, 6, system.input_dim, **dataclasses.asdict(cfg.input))
    together = simulate(system, x0, excitation, **dataclasses.asdict(cfg.simulation))
    for e in (0, 5):
        (alone,) = simulate(system, x0[e:e + 1], Multisine(excitation.amplitude, excitation.f0_hz,
                                                            excitation.phases[e:e + 1], excitation.first_harmonic),
                            **dataclasses.asdict(cfg.simulation))
        np.testing.assert_allclose(together[e].x, alone.x, rtol=0, atol=1e-6 * np.abs(alone.x).max())
        np.testing.assert_array_equal(together[e].u, alone.u)
