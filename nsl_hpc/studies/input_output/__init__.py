"""The input-output study: NARX and SUBNET models identified from measured (or simulated) input-output signals.

    data       the benchmark signals (Silverbox, Wiener-Hammerstein, stand-ins) and their splits
    training   the training loops and free-run simulation of NARX and SUBNET
    study      InputOutput: coordinates, size draws, training and scoring of a task
"""
