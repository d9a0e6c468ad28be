"""The model tests run tiny tensors: one intra-op thread is faster for them than two, and does not
collapse when the other core is busy (OpenMP threads spin-wait on a loaded machine)."""

import torch

torch.set_num_threads(1)
