"""The training-speed benchmark, ``python -m nsl_hpc.bench`` (``__main__``): its input-state and input-output parts."""
