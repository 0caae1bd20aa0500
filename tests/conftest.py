"""Shared test settings: small thread counts so tests behave on a 2-core machine."""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")


def pytest_configure(config):
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # the grasp tests do not need torch
        pass
