import torch

# Deterministic kernels and a fair share of the 2 cores.
torch.set_num_threads(1)
