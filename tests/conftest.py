"""Test-wide settings: tests use small meshes, where one torch thread is fastest and repeatable."""

import torch

torch.set_num_threads(1)
