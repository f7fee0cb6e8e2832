"""The input-state study: models of dx/dt and y from (x, u) samples of simulated port-Hamiltonian systems.

    data       simulated trajectories: training sets and the test set (cached)
    lockstep   the training loop: K models of one shape in lockstep, each as if alone
    stacked    K models' parameters as (K, P) rows and their forward pass
    study      InputState: coordinates, size draws, training and scoring of a task
"""
